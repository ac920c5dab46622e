"""Gymnasium environments for dynamic multi-entity task allocation.

Importing this package registers the ids ``TaskAlloc/<Name>-v0``::

    import gymnasium as gym
    import envs  # noqa: F401  (registers the ids)

    env = gym.make("TaskAlloc/RBF-v0")
"""

from __future__ import annotations

from typing import Any

from gymnasium.envs.registration import register, registry

from envs.almighty import AlmightyEnv, almighty_tables
from envs.core import TaskAllocEnv
from envs.ept import EPTEnv
from envs.mt import MTEnv, generate_trucks
from envs.rbf import RBFEnv
from envs.tables import EntityTable, TaskTable

#: id -> (entry point, kwargs, max_episode_steps). Presets are data: the same classes with other kwargs.
ENV_SPECS: dict[str, tuple[str, dict[str, Any], int]] = {
    "TaskAlloc/Almighty-v0": ("envs.almighty:AlmightyEnv", {}, 1),
    "TaskAlloc/EPT-v0": ("envs.ept:EPTEnv", {"towers": "initial"}, 100),
    "TaskAlloc/EPT-EntityShift-v0": ("envs.ept:EPTEnv", {"towers": "head"}, 100),
    "TaskAlloc/EPT-TaskShift-v0": ("envs.ept:EPTEnv", {"towers": "initial", "reward_scale": 2.5, "arrival_period": 3}, 100),
    "TaskAlloc/RBF-v0": ("envs.rbf:RBFEnv", {}, 100),
    "TaskAlloc/RBF-EntityShift-v0": (
        "envs.rbf:RBFEnv",
        {"entities": "entities_generalization_60", "entity_rows": tuple(range(10, 60))},
        100,
    ),
    "TaskAlloc/RBF-TaskShift-v0": (
        "envs.rbf:RBFEnv",
        {"tasks": "tasks_generalization_alt", "arrival_period": 4, "arrival_count": (3, 8)},
        100,
    ),
    "TaskAlloc/MT-v0": ("envs.mt:MTEnv", {}, 150),
    "TaskAlloc/MT-EntityShift-v0": ("envs.mt:MTEnv", {"n_trucks": 40, "truck_seed": 1}, 150),
    "TaskAlloc/MT-TaskShift-v0": ("envs.mt:MTEnv", {"tasks": "shift", "arrival_period": 4, "arrival_count": (3, 8)}, 150),
}

for _env_id, (_entry, _kwargs, _steps) in ENV_SPECS.items():
    if _env_id not in registry:
        register(id=_env_id, entry_point=_entry, kwargs=_kwargs, max_episode_steps=_steps)

__all__ = [
    "ENV_SPECS",
    "AlmightyEnv",
    "EPTEnv",
    "EntityTable",
    "MTEnv",
    "RBFEnv",
    "TaskAllocEnv",
    "TaskTable",
    "almighty_tables",
    "generate_trucks",
]
