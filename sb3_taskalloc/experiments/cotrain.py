"""Co-training of a manager and bidding workers on the market (the paper's RBF figure f).

:func:`co_train`: a TwoStageSAC manager learning on the market while the workers learn (one DDPG gradient step per env
step, alternating with the manager's updates); either side can be frozen (a trained model or a baseline allocator for
the manager, ``train=False`` for the workers).

CLI: ``python -m sb3_taskalloc.workers --env TaskAlloc/RBF-v0 --timesteps 20000 --out results/workers``. It saves a
checkpoint every ``--checkpoint-every`` steps and at Ctrl-C; the same command started again continues from it.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.utils import set_random_seed

from sb3_taskalloc.common.save_util import check_saved_model
from sb3_taskalloc.common.utils import atomic_path, writable_folder
from sb3_taskalloc.experiments.checkpoint import keep_only
from sb3_taskalloc.experiments.plots import plot_incomes
from sb3_taskalloc.market import BiddingWorkers, WorkerMarket, load_worker_config, make_market
from sb3_taskalloc.zoo_config import config_path


class Manager(Protocol):
    def predict(
        self, observation: Any, state: Any = None, episode_start: Any = None, deterministic: bool = False
    ) -> tuple[np.ndarray, Any]: ...


#: Called after every env step of :func:`co_train` (a learning manager's: before every collection, after the gradient
#: steps of the one before) with the steps done in that call, the manager and the market.
StepHook = Callable[[int, Any, WorkerMarket], None]


def run_manager(
    market: WorkerMarket,
    manager: Manager,
    total_timesteps: int,
    seed: int | None = None,
    hook: StepHook | None = None,
    progress_bar: bool = False,
) -> None:
    """Run a fixed (frozen) manager on the market for ``total_timesteps`` env steps (the workers learn if ``train``)."""
    from tqdm.auto import tqdm

    obs, _ = market.reset(seed=seed)
    for step in tqdm(range(1, total_timesteps + 1), desc="co-training, manager frozen", disable=not progress_bar):
        action, _ = manager.predict(obs, deterministic=True)
        obs, _, terminated, truncated, _ = market.step(action)
        if terminated or truncated:
            obs, _ = market.reset()
        if hook is not None:
            hook(step, manager, market)


class _HookCallback(BaseCallback):
    """Calls a :data:`StepHook` before every collection of a learning manager (every env step at ``train_freq`` 1): the
    previous collection's transitions are stored and its gradient steps done, so a save there is whole."""

    def __init__(self, hook: StepHook, market: WorkerMarket) -> None:
        super().__init__()
        self.hook, self.market = hook, market

    def _on_training_start(self) -> None:
        self.start = self.model.num_timesteps

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        self.hook(self.model.num_timesteps - self.start, self.model, self.market)


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
    hook: StepHook | None = None,
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
    :param progress_bar: a progress bar (SB3's for a learning manager)
    :param hook: a :data:`StepHook` (the CLI saves its checkpoints from it)
    :return: the manager and the market (``market.history`` holds the per-episode incomes); after Ctrl-C, as they
        stand, with a warning
    """
    from sb3_taskalloc.two_stage_sac import TwoStageSAC

    set_random_seed(seed)
    market = make_market(env_id, workers, seed=seed, worker_kwargs=worker_kwargs, train=train_workers)
    if manager is None:
        manager = TwoStageSAC("TAMPolicy", market, seed=seed, **(manager_kwargs or {}))
    elif isinstance(manager, TwoStageSAC):
        manager.set_env(market)
        manager.set_random_seed(seed)  # the market's episodes too: a manager loaded without an env has no seed for them
    try:
        if isinstance(manager, TwoStageSAC) and train_manager:
            callback = None if hook is None else _HookCallback(hook, market)
            manager.learn(total_timesteps, callback=callback, progress_bar=progress_bar, reset_num_timesteps=False)
        else:
            run_manager(market, manager, total_timesteps, seed=seed, hook=hook, progress_bar=progress_bar)
    except KeyboardInterrupt:  # a manager and workers made here would be lost with the exception
        warnings.warn("co-training interrupted (Ctrl-C): the manager and the market are returned as they stand", stacklevel=2)
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


class Checkpoints:
    """The CLI's checkpoints of one co-training run, in one folder per set of arguments: the learning manager and the
    workers, each with its replay buffer, and the incomes of the finished episodes. Each checkpoint is a folder
    ``step_<k>``; ``state.json``, written after it, names the one in force, so a kill during a save leaves the previous
    one in force. Each save also draws the incomes so far (``incomes.csv``, ``incomes.png`` in ``out``), to watch a long
    run by.

    :param folder: where they are kept
    :param every: env steps between checkpoints
    :param save_manager: whether the manager learns, and so is saved
    :param out: where the incomes so far are drawn
    :param title: the figure's title
    """

    def __init__(self, folder: Path, every: int, save_manager: bool, out: Path, title: str) -> None:
        self.folder, self.every, self.save_manager, self.out, self.title = folder, every, save_manager, out, title
        self.done = 0  # steps of the checkpoint this process resumed from
        self.history_before: list[dict[str, float]] = []
        self.last: tuple[int, Any, WorkerMarket] | None = None
        self.saved = 0  # the step of the last save in this process

    def state(self) -> dict[str, Any] | None:
        """The saved state (steps, incomes), or None where no run with these arguments was cut short."""
        path = self.folder / "state.json"
        return json.loads(path.read_text()) if path.is_file() else None

    def step_folder(self, steps: int) -> Path:
        """The folder of the checkpoint at ``steps``."""
        return self.folder / f"step_{steps}"

    def path(self, name: str, steps: int | None = None) -> Path:
        """The file ``name`` of the checkpoint at ``steps`` (default: the one resumed from)."""
        return self.step_folder(self.done if steps is None else steps) / name

    def resume(self, state: dict[str, Any]) -> None:
        """Count the steps and incomes of ``state`` as done."""
        self.done, self.history_before = state["steps"], state["history"]

    def hook(self, step: int, manager: Any, market: WorkerMarket) -> None:
        """A :data:`StepHook`: remember the run's objects, and save every ``every`` steps."""
        self.last = (step, manager, market)
        if step - self.saved >= self.every:
            self.save()

    @property
    def steps(self) -> int:
        """Env steps done, in this process and before it (a learning manager counts its own, up to the last one)."""
        if self.last is None:
            return self.done
        return int(self.last[1].num_timesteps) if self.save_manager else self.done + self.last[0]

    def history(self) -> list[dict[str, float]]:
        """The incomes of every finished episode of the run."""
        return self.history_before + (self.last[2].history if self.last else [])

    def save(self) -> None:
        """Save the run as it stands (nothing before its first step)."""
        if self.last is None:
            return
        self.saved, manager, market = self.last
        steps = self.steps
        if self.save_manager:
            manager.save(self.path("manager.zip", steps))
            manager.save_replay_buffer(self.path("manager_buffer.pkl", steps))
        market.workers.save(self.path("workers", steps))
        market.workers.ddpg.save_replay_buffer(self.path("workers_buffer.pkl", steps))
        history = self.history()
        keep_only(self.folder, self.step_folder(steps), {"steps": steps, "history": history})
        save_history(history, self.out, self.title)

    def clear(self) -> None:
        """Remove the checkpoints of a run that finished."""
        shutil.rmtree(self.folder, ignore_errors=True)


def build_parser() -> argparse.ArgumentParser:
    """The co-training command line."""
    from sb3_taskalloc.experiments.budgets import full_env_id

    parser = argparse.ArgumentParser(
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        prog="python -m sb3_taskalloc.workers",
        description=__doc__.split("\n\n")[0],
    )
    import envs

    parser.add_argument(
        "--env", type=full_env_id, choices=sorted(envs.ENV_SPECS), default="TaskAlloc/RBF-v0", help="TaskAlloc id"
    )
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
    parser.add_argument(
        "--checkpoint-every", type=int, default=1000, help="env steps between checkpoints (the same command resumes)"
    )
    return parser


def write_outputs(out: Path, manager: Any, workers: BiddingWorkers, history: list[dict[str, float]], title: str) -> list[Path]:
    """The run's files in ``out``: the manager (when it learned), the workers and the incomes."""
    written = []
    if manager is not None:
        manager.save(out / "manager.zip")
        written.append(out / "manager.zip")
    workers.save(out / "workers")
    written += [out / "workers.zip", out / "workers.json"]
    return written + save_history(history, out, title)


def starting_point(args: argparse.Namespace, checkpoints: Checkpoints) -> tuple[Any, BiddingWorkers | None]:
    """The manager and workers the run starts from: those of ``--manager`` and ``--workers``, or those of the
    checkpoint of a run with the same arguments that was cut short."""
    from sb3_taskalloc.baselines import GreedyAllocator
    from sb3_taskalloc.two_stage_sac import TwoStageSAC

    manager: Any = None
    if args.manager == "greedy":
        manager = GreedyAllocator()
    elif args.manager != "learn":
        manager = TwoStageSAC.load(args.manager, buffer_size=1)
    workers = BiddingWorkers.load(args.workers, seed=args.seed) if args.workers else None
    state = checkpoints.state()
    if state is None:
        return manager, workers
    checkpoints.resume(state)
    print(f"resuming from the checkpoint at step {checkpoints.done} of {args.timesteps} ({checkpoints.folder})")
    workers = BiddingWorkers.load(checkpoints.path("workers"), seed=args.seed + checkpoints.done)
    workers.ddpg.load_replay_buffer(checkpoints.path("workers_buffer.pkl"))
    if args.manager == "learn":
        manager = TwoStageSAC.load(checkpoints.path("manager.zip"))
        manager.load_replay_buffer(checkpoints.path("manager_buffer.pkl"))
    return manager, workers


def report(history: list[dict[str, float]], written: list[Path]) -> None:
    """Print the last episodes' mean incomes and the files written."""
    last = history[-5:]
    if last:
        means = {
            k: float(np.mean([h[k] for h in last])) for k in ("manager_income", "worker_income", "total_income", "mean_bid")
        }
        print(f"last {len(last)} episodes: " + ", ".join(f"{k} {v:.3f}" for k, v in means.items()))
    else:
        print("no episode ended within --timesteps: no incomes.csv or incomes.png")
    print("wrote " + ", ".join(str(p) for p in written))


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.timesteps < 1 or args.checkpoint_every < 1:
        parser.error(f"--timesteps and --checkpoint-every must be >= 1, got {args.timesteps}, {args.checkpoint_every}")
    if args.conf_file is not None and not Path(args.conf_file).is_file():
        parser.error(f"--conf-file {args.conf_file} does not exist")
    if args.manager not in ("learn", "greedy"):
        try:
            check_saved_model(args.manager, ["data", "policy.pth"])
        except (OSError, ValueError) as error:
            parser.error(f"--manager is neither learn, greedy nor a saved model: {error}")
    missing = [str(Path(args.workers).with_suffix(s)) for s in (".zip", ".json")] if args.workers else []
    if any(not Path(path).is_file() for path in missing):
        parser.error(f"--workers {args.workers} needs {' and '.join(missing)}, as BiddingWorkers.save writes them")
    conf_file = Path(args.conf_file) if args.conf_file else DEFAULT_CONF
    try:
        worker_kwargs = load_worker_config(conf_file, args.env) if conf_file.is_file() else {}
    except ValueError as error:
        parser.error(str(error))
    out = writable_folder(args.out)  # before training: an unwritable folder must not cost a run
    from sb3_taskalloc.experiments.budgets import config_key

    th.set_num_threads(1)
    learn = args.manager == "learn"
    key = {k: v for k, v in vars(args).items() if k not in ("out", "conf_file", "checkpoint_every")}
    title = f"{args.env}: manager ({args.manager}) and bidding workers"
    checkpoints = Checkpoints(out / f"checkpoint_{config_key(key, worker_kwargs)}", args.checkpoint_every, learn, out, title)
    manager, workers = starting_point(args, checkpoints)
    if args.timesteps > checkpoints.done:
        manager, market = co_train(
            args.env,
            args.timesteps - checkpoints.done,
            manager,
            workers,
            train_workers=not args.freeze_workers,
            train_manager=learn,
            seed=args.seed + checkpoints.done,
            worker_kwargs=worker_kwargs,
            progress_bar=True,
            hook=checkpoints.hook,
        )
        workers = market.workers
    if checkpoints.steps < args.timesteps:  # stopped by Ctrl-C, which co_train turns into an early return
        checkpoints.save()
        if checkpoints.last is not None:
            written = write_outputs(out, manager if learn else None, market.workers, checkpoints.history(), title)
            print(f"interrupted at step {checkpoints.steps} of {args.timesteps}: wrote " + ", ".join(map(str, written)))
            print("the same command continues from there")
        else:
            print(f"interrupted before its first step here: the run stays at step {checkpoints.done} of {args.timesteps}")
        raise SystemExit(130)
    assert workers is not None
    history = checkpoints.history()
    report(history, write_outputs(out, manager if learn else None, workers, history, title))
    checkpoints.clear()


if __name__ == "__main__":
    main()
