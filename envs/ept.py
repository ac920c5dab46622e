"""Electric Power Transportation (EPT)."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

from envs.core import TaskAllocEnv
from envs.tables import EntityTable, TaskTable, load_table


class EPTEnv(TaskAllocEnv):
    """## Description

    Twenty power towers connected by wires. Towers that reach peak demand become tasks (reward and power need are
    the tower's base values × ``reward_scale`` = 2, the peak); the other towers are entities that transmit power to
    them. The cost of tower i serving task tower j is the Euclidean distance between them times the mean wire cost
    of the pair. Towers are never busy: every step is a fresh allocation, and a task completes when the power sent to
    it covers its demand. Demands change every step (relative noise ``demand_noise``) and decay (×0.9 after 10
    steps). A task tower is released back into the pool when its task completes.

    Differences from the published code, which had these as bugs: the task tower's own wire cost, only reward and
    power doubled, decay of reward and power only, the task's own tower released, every empty slot refilled.

    ## Arguments

    ``towers``: ``"initial"`` (the training table) or ``"head"`` (the entity-shift table), ``arrival``
    (``"random"``: towers not already tasks reach their peak at random; ``"reference"``: the published 30-task
    sequence) and every keyword of :class:`envs.core.TaskAllocEnv`.
    """

    def __init__(self, towers: Literal["initial", "head"] = "initial", **kwargs: Any) -> None:
        data = load_table("ept")
        key = {"initial": "towers_initial_commit", "head": "towers_head"}.get(towers)
        if key is None:
            raise ValueError(f"towers must be 'initial' or 'head', got {towers!r}")
        table = np.asarray(data[key], dtype=np.float64)
        entities = EntityTable(
            cost=np.zeros(len(table)), supply=table[:, 1:2], positions=table[:, 2:4], wire_cost=data["convey_cost"]
        )
        if kwargs.get("arrival", "random") == "reference":
            seq = np.asarray(data["task_sequence"], dtype=np.int64)
            tasks = TaskTable(rows=table[seq, :2], towers=seq)
        else:
            tasks = TaskTable(rows=table[:, :2], towers=np.arange(len(table)))
        defaults: dict[str, Any] = dict(
            max_tasks=5,
            grid_size=100,
            travel="none",
            busy=False,
            reward_scale=2.0,
            demand_noise=0.1,
            decay=0.9,
            decay_after=10,
        )
        super().__init__(entities, tasks, **{**defaults, **kwargs})
