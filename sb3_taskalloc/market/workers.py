"""Self-interested worker entities that bid their wage with SB3's DDPG (the paper's Demand Module).

Workers are the entities of a ``bidding=True`` env. Before every allocation each free worker sees its own attributes
and the open task nearest to it (the task it is offered) and posts a bid, its wage, in ``[0, bid_max]``; the env
charges the accepted bids (plus travel) to the manager. A worker earns its bid when it was picked for a task that
completes, else 0: a one-shot (bandit) transition, settled when its task completes or the episode ends.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3 import DDPG
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.save_util import load_from_zip_file

from sb3_taskalloc.common.utils import atomic_path, atomic_write_text


class FeatureLayout(Protocol):
    """The columns of the cells in ``entity_features`` and ``task_features`` (``envs.layout.ObsLayout``)."""

    @property
    def position(self) -> slice: ...

    @property
    def task_position(self) -> slice: ...


def worker_observations(
    obs: dict[str, np.ndarray], base_cost: np.ndarray, layout: FeatureLayout
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What each free worker sees when it bids: its own attributes and the open task nearest to it.

    :param obs: one observation of a bidding env
    :param base_cost: (N,) the workers' own base costs (their table costs, private to them)
    :param layout: the env's feature columns (``env.unwrapped.layout``)
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
    pos_e, pos_t = ef[free, layout.position], tf[open_, layout.task_position]
    dist = np.abs(pos_e[:, None, :] - pos_t[None, :, :]).sum(-1)  # (n, open)
    nearest = open_[np.argmin(dist, axis=1)]
    d = dist.min(axis=1)
    supply, demand = obs["entity_supply"][free], obs["task_demand"][nearest]
    cover = np.minimum(supply, demand).sum(1) / np.maximum(demand.sum(1), 1e-6)
    x = np.column_stack(
        [base_cost[free], supply, pos_e, obs["task_reward"][nearest], demand, tf[nearest, layout.task_position], d, cover]
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
        self.ddpg.set_logger(Logger(None, []))  # silent, and no log folder (SB3's configure() makes one in /tmp)
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
        with atomic_path(path.with_suffix(".zip")) as tmp:
            self.ddpg.save(tmp)
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
        atomic_write_text(path.with_suffix(".json"), json.dumps(state, indent=2))

    @classmethod
    def load(cls, path: str | Path, seed: int | None = None, device: str = "auto") -> BiddingWorkers:
        """Load workers saved by :meth:`save` (the policy, its DDPG settings and σ; the replay buffer starts empty)."""
        path = Path(path)
        state = json.loads(path.with_suffix(".json").read_text())
        # The network's shape and the optimiser's settings are DDPG's own, saved in its zip (SB3 pickles them).
        data, _, _ = load_from_zip_file(path.with_suffix(".zip"), device=device)
        if data is None:
            raise ValueError(f"{path.with_suffix('.zip')} holds no DDPG settings: not saved by BiddingWorkers.save")
        workers = cls(
            state["n_resources"],
            state["bid_max"],
            init_bid=state["init_bid"],
            sigma=tuple(state["sigma"]),  # type: ignore[arg-type]
            sigma_decay=state["sigma_decay"],
            batch_size=state["batch_size"],
            learning_starts=state["learning_starts"],
            gradient_steps=state["gradient_steps"],
            learning_rate=data["learning_rate"],
            buffer_size=data["buffer_size"],
            policy_kwargs=data["policy_kwargs"],
            seed=seed,
            device=device,
        )
        workers.ddpg.set_parameters(str(path.with_suffix(".zip")), device=device)
        return workers
