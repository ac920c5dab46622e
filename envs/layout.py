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
