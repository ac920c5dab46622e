"""Greedy and random allocators."""

from __future__ import annotations

import numpy as np

from sb3_taskalloc.baselines.base import Allocator

#: Remaining demand below this counts as covered (stricter than the environments' tolerance).
COVER_TOL = 1e-5


class GreedyAllocator(Allocator):
    """Per open task, by decreasing reward: add the free entity with the lowest pair cost per unit of remaining
    demand it covers, until the task is covered; keep the team only if reward − Σ pair costs > 0."""

    def allocate(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        free = obs["entity_mask"].astype(bool).copy()
        open_ = obs["task_mask"].astype(bool)
        supply, demand = obs["entity_supply"].astype(np.float64), obs["task_demand"].astype(np.float64)
        reward, pc = obs["task_reward"].astype(np.float64), obs["pair_cost"].astype(np.float64)
        N, M = len(free), len(open_)
        action = np.full(N, M, dtype=np.int64)
        for j in sorted(np.flatnonzero(open_), key=lambda j: -reward[j]):
            rem = demand[j].copy()
            cand = free.copy()
            team: list[int] = []
            cost = 0.0
            while rem.max(initial=0.0) > COVER_TOL and cand.any():
                useful = np.minimum(supply, rem).sum(1)
                ratio = np.where(cand & (useful > 0), pc[:, j] / np.maximum(useful, 1e-12), np.inf)
                i = int(np.argmin(ratio))
                if not np.isfinite(ratio[i]):
                    break
                team.append(i)
                cand[i] = False
                rem = np.maximum(rem - supply[i], 0.0)
                cost += pc[i, j]
            if rem.max(initial=0.0) <= COVER_TOL and reward[j] - cost > 0:
                action[team] = j
                free[team] = False
        return action


class RandomAllocator(Allocator):
    """Each entity picks uniformly among its valid choices (open tasks and "unassigned").

    :param seed: seed of the allocator's own generator
    """

    def __init__(self, seed: int | None = None) -> None:
        self.rng = np.random.default_rng(seed)

    def reset(self, seed: int | None = None) -> None:
        if seed is not None:
            self.rng = np.random.default_rng(seed)

    def allocate(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        mask = obs["action_mask"].reshape(len(obs["entity_mask"]), -1).astype(bool)
        return np.argmax(self.rng.random(mask.shape) + mask, axis=1)
