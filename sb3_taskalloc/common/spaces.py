"""The ``TaskAlloc`` observation and action layout that the policies read."""

from __future__ import annotations

import numpy as np
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


def check_observation(observation: object, observation_space: spaces.Dict) -> None:
    """Raise a clear error unless ``observation`` (what a user hands to ``predict``) is a dict with the keys of
    ``observation_space``, as many entities and tasks, and finite values (NaN would give a normal-looking action)."""
    if not isinstance(observation, dict):
        raise ValueError(f"TAMPolicy expects a TaskAlloc observation dict, got {type(observation).__name__}")
    expected = set(observation_space.spaces)
    if set(observation) != expected:
        missing, extra = sorted(expected - set(observation)), sorted(set(observation) - expected)
        raise ValueError(f"the observation's keys do not match the model's space: missing {missing}, unexpected {extra}")
    # The policy is size-agnostic, but SB3's predict checks shapes against the space: name the sizes and the remedy.
    n, m = (np.shape(observation[key])[-1] if np.ndim(observation[key]) else 0 for key in ("entity_mask", "task_mask"))
    N, M = observation_space["entity_mask"].shape[-1], observation_space["task_mask"].shape[-1]  # type: ignore[index]
    if np.shape(observation["pair_cost"])[-2:] != (n, m):
        raise ValueError(
            f"the observation's arrays disagree on its size: {n} entities in entity_mask, {m} tasks in task_mask, "
            f"pair_cost of shape {np.shape(observation['pair_cost'])}"
        )
    if (n, m) != (N, M):
        raise ValueError(
            f"the observation has {n} entities and {m} tasks, the model's space {N} and {M}: the policy runs on any "
            "size once the model has an env of that size (model.set_env(env), or TwoStageSAC.load(path, env=env))"
        )
    for key in OBS_KEYS:
        value = np.asarray(observation[key])
        if value.dtype.kind == "f" and not np.isfinite(value).all():
            raise ValueError(f"observation[{key!r}] contains NaN or infinite values")
