"""The bidding market around a ``bidding=True`` env: workers bid, the manager allocates, wages are settled."""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any, Protocol, cast

import gymnasium as gym
import numpy as np

from sb3_taskalloc.market.workers import BiddingWorkers, worker_observations


class BiddingEnv(Protocol):
    """The public interface of a ``TaskAlloc`` env built with ``bidding=True`` that the market uses."""

    bidding: bool
    K: int
    bid_max: float
    max_tasks: int

    @property
    def layout(self) -> Any: ...

    @property
    def base_costs(self) -> np.ndarray: ...

    @property
    def bids(self) -> np.ndarray: ...

    def set_bids(self, bids: np.ndarray) -> None: ...

    def observe(self) -> dict[str, np.ndarray]: ...

    def applied_action(self) -> np.ndarray: ...


def bidding_env(env: gym.Env) -> BiddingEnv:
    """The ``bidding=True`` TaskAlloc env under ``env``'s wrappers, or a clear error."""
    base = env.unwrapped
    if not getattr(base, "bidding", False):
        raise ValueError("the bidding market needs a TaskAlloc env built with bidding=True")
    return cast(BiddingEnv, base)


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
        base = bidding_env(env)
        if abs(base.bid_max - workers.bid_max) > 1e-9 or workers.n_resources != base.K:
            raise ValueError(
                f"workers were built for K={workers.n_resources}, bid_max={workers.bid_max}; "
                f"the env has K={base.K}, bid_max={base.bid_max}"
            )
        self.base = base
        self.workers = workers
        self.train = train
        self.explore = train if explore is None else explore
        self.base_cost = base.base_costs  # the workers' own table costs
        self.history: list[dict[str, float]] = []
        self._pending: dict[int, tuple[np.ndarray, float]] = {}
        self._offer: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def _post_bids(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        idx, _, x = worker_observations(obs, self.base_cost, self.base.layout)
        bids = self.base.bids
        offered = self.workers.bid(x, explore=self.explore)
        bids[idx] = offered
        self.base.set_bids(bids)
        self._offer = (idx, x, offered)
        self.last_bids = bids
        return self.base.observe()

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
        committed = obs["entity_features"][:, self.base.layout.busy] > 0
        applied = self.base.applied_action()
        paid = np.zeros(len(committed))
        assert self._offer is not None, "reset() the market first"
        idx, x, offered = self._offer
        for row, (i, bid) in enumerate(zip(idx.tolist(), offered.tolist(), strict=True)):
            if applied[i] < self.base.max_tasks:
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
    if workers is None:
        base = bidding_env(env)
        workers = BiddingWorkers(base.K, base.bid_max, seed=seed, **(worker_kwargs or {}))
    return WorkerMarket(env, workers, **kwargs)
