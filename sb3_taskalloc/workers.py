"""Self-interested worker entities that bid their wage with SB3's DDPG, co-trained with the manager.

Workers are the entities of a ``bidding=True`` env. Before every allocation each free worker sees its own attributes
and the open task nearest to it (the task it is offered) and posts a bid, its wage, in ``[0, bid_max]``; the env
charges the accepted bids (plus travel) to the manager. A worker earns its bid when it was picked for a task that
completes, else 0: a one-shot (bandit) transition, settled when its task completes or the episode ends.

- :class:`BiddingWorkers`: one SB3 ``DDPG`` whose shared policy bids for every worker, with Gaussian exploration whose
  σ decays from 0.5 to 0.05 (paper), and its replay buffer of settled bids.
- :class:`WorkerMarket`: a ``gymnasium.Wrapper`` that runs the market around the env: it posts the workers' bids
  before each manager decision, settles their rewards after it, trains the workers (one DDPG gradient step per env
  step, alternating with the manager's updates) and logs manager, worker and total income per episode.
- :func:`co_train`: a TwoStageSAC manager learning on the market while the workers learn; either side can be frozen
  (a trained model or a baseline allocator for the manager, ``train=False`` for the workers).

CLI: ``python -m sb3_taskalloc.workers --env TaskAlloc/RBF-v0 --timesteps 20000 --out results/workers``.
"""

from __future__ import annotations

import argparse
import csv
import inspect
import json
import math
from pathlib import Path
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import DDPG
from stable_baselines3.common.logger import configure
from stable_baselines3.common.utils import set_random_seed


class Manager(Protocol):
    def predict(
        self, observation: Any, state: Any = None, episode_start: Any = None, deterministic: bool = False
    ) -> tuple[np.ndarray, Any]: ...


def worker_observations(obs: dict[str, np.ndarray], base_cost: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What each free worker sees when it bids: its own attributes and the open task nearest to it.

    :param obs: one observation of a bidding env
    :param base_cost: (N,) the workers' own base costs (their table costs, private to them)
    :return: indices of the bidding workers (free, with an open task), their offered task slots, and their observations
        (n, 2K + 8): symlog of [base cost, supply (K), x, y] + [task reward, remaining demand (K), x, y] + [distance,
        share of the task's remaining demand the worker covers]
    """
    K = obs["entity_supply"].shape[1]
    free = np.flatnonzero(obs["entity_mask"])
    open_ = np.flatnonzero(obs["task_mask"])
    if free.size == 0 or open_.size == 0:
        return free[:0], free[:0], np.zeros((0, 2 * K + 8), dtype=np.float32)
    ef, tf = obs["entity_features"], obs["task_features"]
    pos_e, pos_t = ef[free, 1 + K : 3 + K], tf[open_, 1 + K : 3 + K]
    dist = np.abs(pos_e[:, None, :] - pos_t[None, :, :]).sum(-1)  # (n, open)
    nearest = open_[np.argmin(dist, axis=1)]
    d = dist.min(axis=1)
    supply, demand = obs["entity_supply"][free], obs["task_demand"][nearest]
    cover = np.minimum(supply, demand).sum(1) / np.maximum(demand.sum(1), 1e-6)
    x = np.column_stack(
        [base_cost[free], supply, pos_e, obs["task_reward"][nearest], demand, tf[nearest, 1 + K : 3 + K], d, cover]
    )
    return free, nearest, (np.sign(x) * np.log1p(np.abs(x))).astype(np.float32)


class _BidSpaces(gym.Env):
    """Spaces of one worker's decision for DDPG (it is trained on the market's transitions, never stepped)."""

    def __init__(self, obs_dim: int, bid_max: float) -> None:
        self.observation_space = spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
        self.action_space = spaces.Box(0.0, bid_max, (1,), np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        return np.zeros(self.observation_space.shape, np.float32), {}  # type: ignore[arg-type]

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        raise RuntimeError("the worker spaces env is not stepped: workers learn from WorkerMarket transitions")


class BiddingWorkers:
    """The workers' shared bidding policy: one SB3 ``DDPG`` for all of them.

    :param n_resources: K of the env
    :param bid_max: largest bid (the env's ``bid_max``)
    :param init_bid: bid the untrained policy posts (default: ``bid_max`` / 20); workers start by asking a low wage
    :param sigma: (start, minimum) std of the Gaussian exploration noise on bids, in bid units (paper: 0.5 → 0.05)
    :param sigma_decay: factor applied to σ after every market round (env step)
    :param learning_rate: DDPG learning rate
    :param buffer_size: DDPG replay buffer size (settled bids)
    :param batch_size: DDPG minibatch size
    :param learning_starts: settled bids before the first update
    :param gradient_steps: DDPG gradient steps per market round
    :param policy_kwargs: DDPG policy keyword arguments
    :param seed: seed of DDPG and of the exploration noise
    :param device: torch device
    """

    def __init__(
        self,
        n_resources: int,
        bid_max: float,
        init_bid: float | None = None,
        sigma: tuple[float, float] = (0.5, 0.05),
        sigma_decay: float = 0.999,
        learning_rate: float = 3e-4,
        buffer_size: int = 100_000,
        batch_size: int = 256,
        learning_starts: int = 5000,
        gradient_steps: int = 1,
        policy_kwargs: dict[str, Any] | None = None,
        seed: int | None = None,
        device: str = "auto",
    ) -> None:
        if bid_max <= 0:
            raise ValueError(f"bid_max must be > 0, got {bid_max}")
        if not 0 < sigma_decay <= 1 or sigma[0] < sigma[1] or sigma[1] < 0:
            raise ValueError(f"need sigma = (start >= min >= 0) and 0 < sigma_decay <= 1, got {sigma}, {sigma_decay}")
        self.n_resources, self.bid_max = n_resources, float(bid_max)
        self.sigma, self.sigma_min, self.sigma_decay = float(sigma[0]), float(sigma[1]), float(sigma_decay)
        self.init_bid = self.bid_max / 20 if init_bid is None else float(init_bid)
        if not 0 <= self.init_bid < self.bid_max:
            raise ValueError(f"init_bid must lie in [0, bid_max={self.bid_max}), got {self.init_bid}")
        self.batch_size, self.learning_starts, self.gradient_steps = batch_size, learning_starts, gradient_steps
        self.rng = np.random.default_rng(seed)
        self.ddpg = DDPG(
            "MlpPolicy",
            _BidSpaces(2 * n_resources + 8, self.bid_max),
            learning_rate=learning_rate,
            buffer_size=buffer_size,
            batch_size=batch_size,
            gamma=0.0,  # bandit: a bid's reward is its whole return
            policy_kwargs=policy_kwargs or {"net_arch": [64, 64]},
            seed=seed,
            device=device,
        )
        self.ddpg.set_logger(configure(None, [""]))
        self._set_initial_bid()

    def _set_initial_bid(self) -> None:
        """Make the untrained actor post about ``init_bid`` whatever it sees (small last layer, tanh-inverted bias)."""
        scaled = 2.0 * self.init_bid / self.bid_max - 1.0
        for actor in (self.ddpg.actor, self.ddpg.actor_target):
            last = [m for m in actor.mu if isinstance(m, th.nn.Linear)][-1]
            with th.no_grad():
                last.weight.mul_(0.01)
                last.bias.fill_(math.atanh(max(min(scaled, 0.999), -0.999)))

    def bid(self, observations: np.ndarray, explore: bool = True) -> np.ndarray:
        """Bids (n,) in [0, bid_max] for worker observations (n, D); with ``explore``, Gaussian noise of std σ."""
        if len(observations) == 0:
            return np.zeros(0)
        bids, _ = self.ddpg.predict(observations, deterministic=True)
        bids = bids.reshape(-1).astype(np.float64)
        if explore:
            bids = bids + self.sigma * self.rng.standard_normal(bids.shape)
        return np.clip(bids, 0.0, self.bid_max)

    def decay_sigma(self) -> None:
        self.sigma = max(self.sigma * self.sigma_decay, self.sigma_min)

    def record(self, observation: np.ndarray, bid: float, reward: float) -> None:
        """Store one settled bid (bandit transition: done, next observation unused)."""
        scaled = self.ddpg.policy.scale_action(np.array([[bid]], dtype=np.float32))
        obs = observation[None].astype(np.float32)
        self.ddpg.replay_buffer.add(obs, obs, scaled, np.array([reward]), np.array([True]), [{}])  # type: ignore[union-attr]

    def update(self) -> bool:
        """DDPG gradient steps once enough bids are settled; :return: whether it trained."""
        if self.ddpg.replay_buffer is None or self.ddpg.replay_buffer.size() < self.learning_starts:
            return False
        self.ddpg.train(self.gradient_steps, self.batch_size)
        return True

    def save(self, path: str | Path) -> None:
        """Save the DDPG model (``<path>.zip``) and the market settings (``<path>.json``)."""
        path = Path(path)
        self.ddpg.save(path.with_suffix(".zip"))
        state = {
            "n_resources": self.n_resources,
            "bid_max": self.bid_max,
            "init_bid": self.init_bid,
            "sigma": [self.sigma, self.sigma_min],
            "sigma_decay": self.sigma_decay,
            "batch_size": self.batch_size,
            "learning_starts": self.learning_starts,
            "gradient_steps": self.gradient_steps,
        }
        path.with_suffix(".json").write_text(json.dumps(state, indent=2))

    @classmethod
    def load(cls, path: str | Path, seed: int | None = None, device: str = "auto") -> BiddingWorkers:
        """Load workers saved by :meth:`save` (the policy and σ; the replay buffer starts empty)."""
        path = Path(path)
        state = json.loads(path.with_suffix(".json").read_text())
        workers = cls(
            state["n_resources"],
            state["bid_max"],
            init_bid=state["init_bid"],
            sigma=tuple(state["sigma"]),  # type: ignore[arg-type]
            sigma_decay=state["sigma_decay"],
            batch_size=state["batch_size"],
            learning_starts=state["learning_starts"],
            gradient_steps=state["gradient_steps"],
            seed=seed,
            device=device,
        )
        workers.ddpg.set_parameters(str(path.with_suffix(".zip")), device=device)
        return workers


class WorkerMarket(gym.Wrapper):
    """Runs the bidding market around a ``bidding=True`` TaskAlloc env; the manager sees the bids in ``pair_cost``.

    Each step: the manager's allocation is applied; the bids of the workers it did not pick settle at 0, those of
    workers whose task completed settle at their bid (the wage fixed when they were picked); the workers train
    (``train=True``); then every free worker bids for the next decision and the returned observation carries the
    new bids. At the end of an episode, unsettled bids settle at 0 and ``info["market"]`` holds the episode's
    manager income (the env return: task rewards − wages − travel), worker income (wages paid) and their total.

    :param env: a TaskAlloc env built with ``bidding=True`` (e.g. ``gym.make("TaskAlloc/RBF-v0", bidding=True)``)
    :param workers: the bidding policy
    :param train: train the workers during the episodes (False: frozen workers)
    :param explore: exploration noise on bids (default: ``train``)
    """

    def __init__(self, env: gym.Env, workers: BiddingWorkers, train: bool = True, explore: bool | None = None) -> None:
        super().__init__(env)
        base = env.unwrapped
        if not getattr(base, "bidding", False):
            raise ValueError("WorkerMarket needs a TaskAlloc env built with bidding=True")
        if abs(base.bid_max - workers.bid_max) > 1e-9 or workers.n_resources != base.K:  # type: ignore[attr-defined]
            raise ValueError(
                f"workers were built for K={workers.n_resources}, bid_max={workers.bid_max}; "
                f"the env has K={base.K}, bid_max={base.bid_max}"  # type: ignore[attr-defined]
            )
        self.workers = workers
        self.train = train
        self.explore = train if explore is None else explore
        self.base_cost = base._cost0  # type: ignore[attr-defined]  # the workers' own table costs
        self.history: list[dict[str, float]] = []
        self._pending: dict[int, tuple[np.ndarray, float]] = {}
        self._offer: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def _post_bids(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        base = self.env.unwrapped
        idx, _, x = worker_observations(obs, self.base_cost)
        bids = base._bid.copy()  # type: ignore[attr-defined]
        offered = self.workers.bid(x, explore=self.explore)
        bids[idx] = offered
        base.set_bids(bids)  # type: ignore[attr-defined]
        self._offer = (idx, x, offered)
        self.last_bids = bids
        return base.observe()  # type: ignore[attr-defined]

    def reset(self, **kwargs: Any) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        self._settle_all()
        obs, info = self.env.reset(**kwargs)
        self._episode = {"manager_income": 0.0, "worker_income": 0.0, "bids_posted": 0.0, "bid_sum": 0.0, "picked": 0.0}
        return self._post_bids(obs), info

    def _settle_all(self) -> None:
        for x, bid in self._pending.values():
            self.workers.record(x, bid, 0.0)
        self._pending = {}

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        obs, env_reward, terminated, truncated, info = self.env.step(action)
        reward = float(env_reward)
        base = self.env.unwrapped
        K = base.K  # type: ignore[attr-defined]
        committed = obs["entity_features"][:, 3 + K] > 0
        applied = base.applied_action()  # type: ignore[attr-defined]
        paid = np.zeros(len(committed))
        assert self._offer is not None, "reset() the market first"
        idx, x, offered = self._offer
        for row, (i, bid) in enumerate(zip(idx.tolist(), offered.tolist(), strict=True)):
            if applied[i] < base.max_tasks:  # type: ignore[attr-defined]
                self._pending[i] = (x[row], bid)  # picked: paid its bid if and when its task completes
                self._episode["picked"] += 1
            else:
                self.workers.record(x[row], bid, 0.0)
        for i in [i for i in self._pending if not committed[i]]:  # released ⇔ its task completed
            xi, bid = self._pending.pop(i)
            self.workers.record(xi, bid, bid)
            paid[i] = bid
        ep = self._episode
        ep["manager_income"] += float(reward)
        ep["worker_income"] += float(paid.sum())
        ep["bids_posted"] += len(offered)
        ep["bid_sum"] += float(offered.sum())
        info["worker_wages"] = paid
        if self.train:
            self.workers.update()
        self.workers.decay_sigma()
        if terminated or truncated:
            self._settle_all()
            record = {
                "manager_income": ep["manager_income"],
                "worker_income": ep["worker_income"],
                "total_income": ep["manager_income"] + ep["worker_income"],
                "mean_bid": ep["bid_sum"] / max(ep["bids_posted"], 1.0),
                "picked": ep["picked"],
                "sigma": self.workers.sigma,
            }
            self.history.append(record)
            info["market"] = record
            return obs, reward, bool(terminated), bool(truncated), info
        return self._post_bids(obs), reward, bool(terminated), bool(truncated), info


def load_worker_config(path: str | Path, env_id: str) -> dict[str, Any]:
    """:class:`BiddingWorkers` keywords of ``env_id`` from a zoo-style YAML file (``zoo_configs/ddpg.yml``); ``{}`` when
    the file has no block for it."""
    import yaml

    config = yaml.safe_load(Path(path).read_text()) or {}
    block = dict(config.get(env_id, {}))
    if "sigma" in block:
        block["sigma"] = tuple(block["sigma"])
    allowed = set(inspect.signature(BiddingWorkers.__init__).parameters) - {"self", "n_resources", "bid_max"}
    unknown = set(block) - allowed
    if unknown:
        raise ValueError(f"{path} [{env_id}]: unknown BiddingWorkers keys {sorted(unknown)}; allowed: {sorted(allowed)}")
    return block


def make_market(
    env_id: str,
    workers: BiddingWorkers | None = None,
    seed: int | None = None,
    worker_kwargs: dict[str, Any] | None = None,
    **kwargs: Any,
) -> WorkerMarket:
    """A :class:`WorkerMarket` on ``gym.make(env_id, bidding=True)``; new workers when none are given.

    :param env_id: a TaskAlloc id (RBF or MT in the paper)
    :param workers: the bidding policy (default: new :class:`BiddingWorkers` for this env, seeded with ``seed``)
    :param seed: seed of the new workers
    :param worker_kwargs: :class:`BiddingWorkers` keywords of new workers (see :func:`load_worker_config`)
    :param kwargs: :class:`WorkerMarket` keywords (``train``, ``explore``)
    """
    env = gym.make(env_id, bidding=True)
    base = env.unwrapped
    if workers is None:
        workers = BiddingWorkers(base.K, base.bid_max, seed=seed, **(worker_kwargs or {}))  # type: ignore[attr-defined]
    return WorkerMarket(env, workers, **kwargs)


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


def save_history(history: list[dict[str, float]], folder: Path, title: str) -> None:
    """Write ``incomes.csv`` and ``incomes.png`` (manager, worker and total income per episode, the paper's RBF
    figure f, with the workers' mean bid on a second axis)."""
    folder.mkdir(parents=True, exist_ok=True)
    if not history:
        return
    with (folder / "incomes.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["episode", *history[0]])
        writer.writeheader()
        for k, row in enumerate(history):
            writer.writerow({"episode": k, **row})
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    ep = np.arange(len(history))
    for key, label in (("total_income", "total"), ("manager_income", "manager"), ("worker_income", "workers")):
        ax.plot(ep, [h[key] for h in history], label=label)
    ax.set_xlabel("episode")
    ax.set_ylabel("income per episode")
    ax2 = ax.twinx()
    ax2.plot(ep, [h["mean_bid"] for h in history], color="grey", linestyle=":", label="mean bid")
    ax2.set_ylabel("mean bid")
    lines = ax.get_legend_handles_labels()
    lines2 = ax2.get_legend_handles_labels()
    ax.legend(lines[0] + lines2[0], lines[1] + lines2[1], loc="best")
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(folder / "incomes.png", dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m sb3_taskalloc.workers", description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="TaskAlloc/RBF-v0", help="TaskAlloc id (RBF or MT)")
    parser.add_argument("--timesteps", type=int, default=20_000, help="env steps")
    parser.add_argument("--out", default="results/workers", help="output folder (models, incomes.csv, incomes.png)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--manager", default="learn", help='"learn" (new TwoStageSAC), "greedy" (frozen baseline) or a saved model (frozen)'
    )
    parser.add_argument("--workers", default=None, help="saved workers to start from (path without suffix)")
    parser.add_argument("--freeze-workers", action="store_true", help="the workers do not learn")
    parser.add_argument("--conf-file", default="zoo_configs/ddpg.yml", help="DDPG settings of new workers (YAML by env id)")
    args = parser.parse_args(argv)
    if args.timesteps < 1:
        parser.error(f"--timesteps must be >= 1, got {args.timesteps}")
    import envs  # noqa: F401  (registers the TaskAlloc ids)
    from sb3_taskalloc.baselines import GreedyAllocator
    from sb3_taskalloc.two_stage_sac import TwoStageSAC

    th.set_num_threads(1)
    manager: Any = None
    if args.manager == "greedy":
        manager = GreedyAllocator()
    elif args.manager != "learn":
        manager = TwoStageSAC.load(args.manager, buffer_size=1)
    workers = BiddingWorkers.load(args.workers, seed=args.seed) if args.workers else None
    worker_kwargs = load_worker_config(args.conf_file, args.env) if Path(args.conf_file).exists() else {}
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
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if isinstance(manager, TwoStageSAC) and args.manager == "learn":
        manager.save(out / "manager.zip")
    market.workers.save(out / "workers")
    save_history(market.history, out, f"{args.env}: manager ({args.manager}) and bidding workers")
    last = market.history[-5:]
    if last:
        means = {
            k: float(np.mean([h[k] for h in last])) for k in ("manager_income", "worker_income", "total_income", "mean_bid")
        }
        print(f"last {len(last)} episodes: " + ", ".join(f"{k} {v:.3f}" for k, v in means.items()))
    print(f"wrote {out}/incomes.csv, incomes.png, workers.zip" + (", manager.zip" if args.manager == "learn" else ""))


if __name__ == "__main__":
    main()
