"""Resource-Based Foraging (RBF)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from envs.core import TaskAllocEnv
from envs.tables import EntityTable, TaskTable, load_table


class RBFEnv(TaskAllocEnv):
    """## Description

    Level-based-foraging-like world on a 7 × 7 grid with three resources. Entities (cost, 3 resources) start at the
    centre cell; apples (reward, 3 requirements) appear at random cells: every 5 steps 5–10 are drawn from the task
    table, capped by free slots. An assigned entity is committed until its apple is harvested: it walks one cell per
    step (4-neighbour, y then x) and works once there. An apple is harvested when the resources of the arrived team
    cover its requirements; then the team is released and the reward minus the team's costs is paid. The cost of an
    entity for an apple is its base cost plus ``travel_cost`` × the Manhattan distance at assignment. Apples older
    than 10 steps lose 1 % of reward and requirements per step.

    Differences from the published code: positions are observed, costs depend on distance (the paper's text),
    only the committed team counts and pays, arrival is
    random as in the paper (``arrival="reference"`` gives the published 30-task list).

    ## Arguments

    ``entities``: name of the entity table in ``rbf.json``; ``entity_rows``: rows of it to use (None: all);
    ``tasks``: name of the task list; and every keyword of :class:`envs.core.TaskAllocEnv`.
    """

    def __init__(
        self,
        entities: str = "entities_train_100",
        entity_rows: Sequence[int] | None = None,
        tasks: str = "tasks_train",
        **kwargs: Any,
    ) -> None:
        data = load_table("rbf")
        if entities not in data or tasks not in data:
            raise ValueError(f"unknown RBF table {entities!r} or {tasks!r}")
        table = np.asarray(data[entities], dtype=np.float64)
        if entity_rows is not None:
            table = table[np.asarray(list(entity_rows), dtype=np.int64)]
        grid = int(data["constants"]["grid_size"])
        start = np.asarray(data["constants"]["entity_start_cell"], dtype=np.int64)
        ents = EntityTable(cost=table[:, 0], supply=table[:, 1:], positions=np.repeat(start[None], len(table), 0))
        task_table = TaskTable(rows=np.asarray(data[tasks], dtype=np.float64), positions=data["task_positions"])
        defaults: dict[str, Any] = dict(
            max_tasks=10, grid_size=grid, travel="manhattan", travel_cost=0.03, decay=0.99, decay_after=10
        )
        super().__init__(ents, task_table, **{**defaults, **kwargs})
