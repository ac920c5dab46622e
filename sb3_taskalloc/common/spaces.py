"""The ``TaskAlloc`` observation and action layout that the policies read."""

from __future__ import annotations

from gymnasium import spaces

#: Keys of the observation that TAMPolicy reads (the ``TaskAlloc`` observation layout).
OBS_KEYS = (
    "entity_features",
    "task_features",
    "entity_supply",
    "task_demand",
    "task_reward",
    "pair_cost",
    "entity_mask",
    "task_mask",
)


def check_spaces(observation_space: spaces.Space, action_space: spaces.Space) -> None:
    """Raise a clear error unless the spaces follow the ``TaskAlloc`` observation and action layout."""
    if not isinstance(observation_space, spaces.Dict) or not set(OBS_KEYS) <= set(observation_space.spaces):
        raise ValueError(
            f"TAMPolicy needs a TaskAlloc Dict observation space with keys {sorted(OBS_KEYS)}, got {observation_space}"
        )
    N = observation_space["entity_mask"].shape[0]  # type: ignore[index]
    M = observation_space["task_mask"].shape[0]  # type: ignore[index]
    if (
        not isinstance(action_space, spaces.MultiDiscrete)
        or action_space.shape != (N,)
        or not (action_space.nvec == M + 1).all()
    ):
        raise ValueError(
            f"TAMPolicy needs MultiDiscrete([{M + 1}] * {N}) actions (M + 1 choices per entity), got {action_space}"
        )
