"""Co-training of a manager and bidding workers on the market (the paper's RBF figure f).

:func:`co_train`: a TwoStageSAC manager learning on the market while the workers learn (one DDPG gradient step per env
step, alternating with the manager's updates); either side can be frozen (a trained model or a baseline allocator for
the manager, ``train=False`` for the workers).

CLI: ``python -m sb3_taskalloc.workers --env TaskAlloc/RBF-v0 --timesteps 20000 --out results/workers``.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch as th
from stable_baselines3.common.utils import set_random_seed

from sb3_taskalloc.common.utils import atomic_path, writable_folder
from sb3_taskalloc.experiments.plots import plot_incomes
from sb3_taskalloc.market import BiddingWorkers, WorkerMarket, load_worker_config, make_market
from sb3_taskalloc.zoo_config import config_path


class Manager(Protocol):
    def predict(
        self, observation: Any, state: Any = None, episode_start: Any = None, deterministic: bool = False
    ) -> tuple[np.ndarray, Any]: ...


def run_manager(market: WorkerMarket, manager: Manager, total_timesteps: int, seed: int | None = None) -> None:
    """Run a fixed (frozen) manager on the market for ``total_timesteps`` env steps (the workers learn if ``train``)."""
    obs, _ = market.reset(seed=seed)
    for _ in range(total_timesteps):
        action, _ = manager.predict(obs, deterministic=True)
        obs, _, terminated, truncated, _ = market.step(action)
        if terminated or truncated:
            obs, _ = market.reset()


def co_train(
    env_id: str,
    total_timesteps: int,
    manager: Any = None,
    workers: BiddingWorkers | None = None,
    train_workers: bool = True,
    train_manager: bool = True,
    seed: int = 0,
    manager_kwargs: dict[str, Any] | None = None,
    worker_kwargs: dict[str, Any] | None = None,
    progress_bar: bool = False,
) -> tuple[Any, WorkerMarket]:
    """Co-train a manager and the workers on a bidding market.

    :param env_id: TaskAlloc id
    :param total_timesteps: env steps
    :param manager: ``None`` (a new TwoStageSAC that learns), a TwoStageSAC (learns on), or anything with
        ``predict`` (frozen: a baseline allocator or a model run deterministically)
    :param workers: the workers (default: new ones)
    :param train_workers: whether the workers learn (False: frozen workers)
    :param train_manager: whether a TwoStageSAC manager learns (False: it acts deterministically, frozen)
    :param seed: seed of everything
    :param manager_kwargs: TwoStageSAC keywords for a new manager
    :param worker_kwargs: :class:`BiddingWorkers` keywords for new workers
    :param progress_bar: SB3 progress bar for a learning manager
    :return: the manager and the market (``market.history`` holds the per-episode incomes)
    """
    from sb3_taskalloc.two_stage_sac import TwoStageSAC

    set_random_seed(seed)
    market = make_market(env_id, workers, seed=seed, worker_kwargs=worker_kwargs, train=train_workers)
    if manager is None:
        manager = TwoStageSAC("TAMPolicy", market, seed=seed, **(manager_kwargs or {}))
    elif isinstance(manager, TwoStageSAC):
        manager.set_env(market)
    if isinstance(manager, TwoStageSAC) and train_manager:
        manager.learn(total_timesteps, progress_bar=progress_bar, reset_num_timesteps=False)
    else:
        run_manager(market, manager, total_timesteps, seed=seed)
    return manager, market


#: The workers' DDPG settings by env id, beside the package in a source checkout.
DEFAULT_CONF = config_path("ddpg.yml")


def save_history(history: list[dict[str, float]], folder: Path, title: str) -> list[Path]:
    """Write ``incomes.csv`` and ``incomes.png`` (manager, worker and total income per episode, the paper's RBF
    figure f, with the workers' mean bid on a second axis) when at least one episode ended; otherwise remove those of an
    earlier run in ``folder``.

    :return: the files written (none without a finished episode)
    """
    folder.mkdir(parents=True, exist_ok=True)
    if not history:  # an earlier run's figures beside this run's models would describe another run
        for name in ("incomes.csv", "incomes.png"):
            (folder / name).unlink(missing_ok=True)
        return []
    with atomic_path(folder / "incomes.csv") as tmp, tmp.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["episode", *history[0]])
        writer.writeheader()
        for k, row in enumerate(history):
            writer.writerow({"episode": k, **row})
    return [folder / "incomes.csv", plot_incomes(history, folder / "incomes.png", title)]


def build_parser() -> argparse.ArgumentParser:
    """The co-training command line."""
    from sb3_taskalloc.experiments.budgets import full_env_id

    parser = argparse.ArgumentParser(
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        prog="python -m sb3_taskalloc.workers",
        description=__doc__.split("\n\n")[0],
    )
    parser.add_argument("--env", type=full_env_id, default="TaskAlloc/RBF-v0", help="TaskAlloc id (RBF or MT)")
    parser.add_argument("--timesteps", type=int, default=20_000, help="env steps")
    parser.add_argument("--out", default="runs/workers", help="output folder (models, incomes.csv, incomes.png)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--manager", default="learn", help='"learn" (new TwoStageSAC), "greedy" (frozen baseline) or a saved model (frozen)'
    )
    parser.add_argument("--workers", default=None, help="saved workers to start from (path without suffix)")
    parser.add_argument("--freeze-workers", action="store_true", help="the workers do not learn")
    parser.add_argument(
        "--conf-file", default=None, help=f"DDPG settings of new workers, YAML by env id (default: {DEFAULT_CONF})"
    )
    return parser


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.timesteps < 1:
        parser.error(f"--timesteps must be >= 1, got {args.timesteps}")
    if args.conf_file is not None and not Path(args.conf_file).is_file():
        parser.error(f"--conf-file {args.conf_file} does not exist")
    conf_file = Path(args.conf_file) if args.conf_file else DEFAULT_CONF
    out = writable_folder(args.out)  # before training: an unwritable folder must not cost a run
    from sb3_taskalloc.baselines import GreedyAllocator
    from sb3_taskalloc.two_stage_sac import TwoStageSAC

    th.set_num_threads(1)
    manager: Any = None
    if args.manager == "greedy":
        manager = GreedyAllocator()
    elif args.manager != "learn":
        manager = TwoStageSAC.load(args.manager, buffer_size=1)
    workers = BiddingWorkers.load(args.workers, seed=args.seed) if args.workers else None
    worker_kwargs = load_worker_config(conf_file, args.env) if conf_file.is_file() else {}
    manager, market = co_train(
        args.env,
        args.timesteps,
        manager,
        workers,
        train_workers=not args.freeze_workers,
        train_manager=args.manager == "learn",
        seed=args.seed,
        worker_kwargs=worker_kwargs,
        progress_bar=True,
    )
    written = []
    if isinstance(manager, TwoStageSAC) and args.manager == "learn":
        manager.save(out / "manager.zip")
        written.append(out / "manager.zip")
    market.workers.save(out / "workers")
    written += [out / "workers.zip", out / "workers.json"]
    written += save_history(market.history, out, f"{args.env}: manager ({args.manager}) and bidding workers")
    last = market.history[-5:]
    if last:
        means = {
            k: float(np.mean([h[k] for h in last])) for k in ("manager_income", "worker_income", "total_income", "mean_bid")
        }
        print(f"last {len(last)} episodes: " + ", ".join(f"{k} {v:.3f}" for k, v in means.items()))
    else:
        print("no episode ended within --timesteps: no incomes.csv or incomes.png")
    print("wrote " + ", ".join(str(p) for p in written))


if __name__ == "__main__":
    main()
