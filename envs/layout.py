"""The column layout of the ``entity_features`` and ``task_features`` observations, defined once.

Every ``TaskAlloc`` env exposes its layout as ``env.unwrapped.layout``; code that reads a column by meaning (the bidding
market, tests) asks the layout instead of repeating offsets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gymnasium import spaces

#: Upper bound declared for the float features of the observation space (values are far below it in practice).
FEATURE_HIGH = 1e6


@dataclass(frozen=True)
class ObsLayout:
    """Columns of the padded feature matrices for K resources.

    ``entity_features`` (N, K + 5): cost, supply (K), x, y, busy, bid. ``task_features`` (M, K + 4): reward,
    remaining demand (K), x, y, age.

    :param n_resources: K
    """

    n_resources: int

    # entity_features
    cost: int = 0

    @property
    def supply(self) -> slice:
        return slice(1, 1 + self.n_resources)

    @property
    def position(self) -> slice:
        """The entity's cell (x, y)."""
        return slice(1 + self.n_resources, 3 + self.n_resources)

    @property
    def busy(self) -> int:
        """Steps to arrival + 1 while committed (1 when there is no travel), 0 when free."""
        return 3 + self.n_resources

    @property
    def bid(self) -> int:
        return 4 + self.n_resources

    @property
    def n_entity_features(self) -> int:
        return 5 + self.n_resources

    # task_features
    reward: int = 0

    @property
    def demand(self) -> slice:
        return slice(1, 1 + self.n_resources)

    @property
    def task_position(self) -> slice:
        """The task's cell (x, y)."""
        return slice(1 + self.n_resources, 3 + self.n_resources)

    @property
    def age(self) -> int:
        return 3 + self.n_resources

    @property
    def n_task_features(self) -> int:
        return 4 + self.n_resources

    def observation_space(self, n_entities: int, n_tasks: int) -> spaces.Dict:
        """The padded ``Dict`` observation space for N = ``n_entities`` entity rows and M = ``n_tasks`` task slots."""
        N, M, K, f32 = n_entities, n_tasks, self.n_resources, np.float32
        return spaces.Dict(
            {
                "entity_features": spaces.Box(0.0, FEATURE_HIGH, (N, self.n_entity_features), f32),
                "task_features": spaces.Box(0.0, FEATURE_HIGH, (M, self.n_task_features), f32),
                "entity_supply": spaces.Box(0.0, FEATURE_HIGH, (N, K), f32),
                "task_demand": spaces.Box(0.0, FEATURE_HIGH, (M, K), f32),
                "task_reward": spaces.Box(0.0, FEATURE_HIGH, (M,), f32),
                "pair_cost": spaces.Box(0.0, FEATURE_HIGH, (N, M), f32),
                "entity_mask": spaces.MultiBinary(N),
                "task_mask": spaces.MultiBinary(M),
                "action_mask": spaces.MultiBinary(N * (M + 1)),
            }
        )

    def entity_features(self, cost: np.ndarray, supply: np.ndarray, position: np.ndarray, bid: np.ndarray) -> np.ndarray:
        """(N, K + 5) float32 ``entity_features`` with the busy column at 0 (the env fills it every step)."""
        ef = np.zeros((len(cost), self.n_entity_features), dtype=np.float32)
        ef[:, self.cost] = cost
        ef[:, self.supply] = supply
        ef[:, self.position] = position
        ef[:, self.bid] = bid
        return ef

    def task_features(self, reward: np.ndarray, remaining: np.ndarray, position: np.ndarray, age: np.ndarray) -> np.ndarray:
        """(M, K + 4) float32 ``task_features``."""
        tf = np.empty((len(reward), self.n_task_features), dtype=np.float32)
        tf[:, self.reward] = reward
        tf[:, self.demand] = remaining
        tf[:, self.task_position] = position
        tf[:, self.age] = age
        return tf

    @staticmethod
    def action_mask(entity_mask: np.ndarray, task_mask: np.ndarray) -> np.ndarray:
        """(N·(M+1),) int8 mask in sb3-contrib's MultiDiscrete layout: per entity, M task choices then "unassigned"."""
        N, M = len(entity_mask), len(task_mask)
        m = np.empty((N, M + 1), dtype=bool)
        np.multiply.outer(entity_mask, task_mask, out=m[:, :M])
        m[:, M] = True
        return m.reshape(-1).view(np.int8)

    def observation(
        self, ef: np.ndarray, tf: np.ndarray, pair_cost: np.ndarray, entity_mask: np.ndarray, task_mask: np.ndarray
    ) -> dict[str, np.ndarray]:
        """The observation dict from the feature matrices, pair costs and masks (the other keys are their columns)."""
        return {
            "entity_features": ef,
            "task_features": tf,
            "entity_supply": ef[:, self.supply].copy(),
            "task_demand": tf[:, self.demand].copy(),
            "task_reward": tf[:, self.reward].copy(),
            "pair_cost": pair_cost,
            "entity_mask": entity_mask.astype(np.int8),
            "task_mask": task_mask.astype(np.int8),
            "action_mask": self.action_mask(entity_mask, task_mask),
        }
