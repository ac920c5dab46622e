"""Retain the Almighty: the one-step toy of the paper's first experiment."""

from __future__ import annotations

from typing import Any

import numpy as np

from envs.core import TaskAllocEnv
from envs.tables import EntityTable, TaskTable, load_table


def almighty_tables(
    n_skills: int = 8, specialists: int = 3, single_reward: float = 3.0, almighty_reward: float = 20.0
) -> tuple[EntityTable, TaskTable]:
    """Build the Almighty instance: ``specialists`` entities per skill plus one almighty entity (all skills), all of
    cost 1; ``n_skills`` single-skill tasks and one task that needs every skill.

    With the defaults this is the published 25 × 9 instance (``envs/data/almighty.json``), optimum 35.
    """
    if n_skills < 1 or specialists < 1:
        raise ValueError(f"n_skills and specialists must be >= 1, got {n_skills}, {specialists}")
    skills = np.zeros((n_skills * specialists + 1, n_skills))
    for k in range(n_skills):
        skills[k * specialists : (k + 1) * specialists, k] = 1.0
    skills[-1] = 1.0
    tasks = np.zeros((n_skills + 1, n_skills + 1))
    tasks[:n_skills, 0] = single_reward
    tasks[np.arange(n_skills), 1 + np.arange(n_skills)] = 1.0
    tasks[n_skills] = [almighty_reward] + [1.0] * n_skills
    return EntityTable(cost=np.ones(len(skills)), supply=skills), TaskTable(rows=tasks)


class AlmightyEnv(TaskAllocEnv):
    """## Description

    "Retain the Almighty" (paper, first experiment). Every entity costs 1. ``specialists`` entities hold each of the
    ``n_skills`` skills, one almighty entity holds all of them. Tasks ``0..n_skills-1`` need one skill each and pay
    ``single_reward``; the last task needs every skill and pays ``almighty_reward``. The optimum keeps the almighty
    entity for the last task (published instance: 8 × 2 + 20 − 1 = 35). Sequential allocation tends to spend the
    almighty entity on an early single-skill task.

    ## Episode End

    One step: the allocation is scored and the episode terminates. Entities of incomplete tasks cost nothing.

    ## Arguments

    ``n_skills``, ``specialists``, ``single_reward``, ``almighty_reward`` and every keyword of
    :class:`envs.core.TaskAllocEnv` (``max_entities`` pads for size transfer).
    """

    def __init__(
        self,
        n_skills: int = 8,
        specialists: int = 3,
        single_reward: float = 3.0,
        almighty_reward: float = 20.0,
        **kwargs: Any,
    ) -> None:
        entities, tasks = almighty_tables(n_skills, specialists, single_reward, almighty_reward)
        if (n_skills, specialists, single_reward, almighty_reward) == (8, 3, 3.0, 20.0):
            data = load_table("almighty")  # the published instance, from the data file
            rows = np.asarray(data["entities"], dtype=np.float64)
            entities = EntityTable(cost=rows[:, 0], supply=rows[:, 1:])
            tasks = TaskTable(rows=np.asarray(data["tasks"], dtype=np.float64))
        kwargs.setdefault("max_tasks", n_skills + 1)
        kwargs.setdefault("arrival", "static")
        kwargs.setdefault("one_step", True)
        super().__init__(entities, tasks, **kwargs)
