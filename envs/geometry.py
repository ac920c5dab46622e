"""Geometry of the worlds: distances, one step of travel, and what an entity costs for a task.

Cells are integer (x, y) pairs stored as floats. Committed entities move one cell per step towards their task:
``"manhattan"`` (4-neighbour, y first, then x) or ``"chebyshev"`` (8-neighbour); with ``"none"`` they work at once.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from scipy.spatial.distance import cdist

Travel = Literal["none", "manhattan", "chebyshev"]

#: The distance each travel mode moves by (Euclidean when nothing moves: EPT's wires).
METRICS: dict[str, str] = {"none": "euclidean", "manhattan": "cityblock", "chebyshev": "chebyshev"}


def distances(entity_pos: np.ndarray, task_pos: np.ndarray, travel: Travel) -> np.ndarray:
    """(N, M) distance from every entity to every task slot in the travel mode's metric."""
    return cdist(entity_pos, task_pos, METRICS[travel])


def travel_step(
    entity_pos: np.ndarray, target: np.ndarray, committed: np.ndarray, travel: Travel
) -> tuple[np.ndarray, np.ndarray]:
    """One step of travel of the committed entities.

    :param entity_pos: (N, 2) cells, moved in place
    :param target: (N, 2) the cell of each entity's task (anything for free entities)
    :param committed: (N,) bool
    :return: the moved cells and which committed entities were at their task's cell before the move (they work)
    """
    delta = target - entity_pos
    arrived = committed & ~delta.any(1)
    move = np.sign(delta)
    if travel == "manhattan":  # 4-neighbour: align y first, then x
        move[:, 0] *= move[:, 1] == 0
    move *= committed[:, None]
    entity_pos += move
    return entity_pos, arrived


def pair_costs(
    base: np.ndarray, dist: np.ndarray, travel_cost: float, wire: np.ndarray | None, task_entity: np.ndarray
) -> np.ndarray:
    """(N, M) what entity i is charged if it serves task j: its base cost plus ``travel_cost`` × the distance, or, when
    tasks are entities joined by wires (EPT), the distance × the mean wire cost of the two (the task's own wire).

    :param base: (N,) base costs (or bids)
    :param wire: (N,) wire cost per unit of distance of each entity, or None
    :param task_entity: (M,) the entity that is task j (−1: none)
    """
    if wire is not None:
        return base[:, None] + dist * (0.5 * (wire[:, None] + wire[task_entity]))
    return base[:, None] + travel_cost * dist


def static_tower_costs(
    entity_pos: np.ndarray, wire: np.ndarray, towers: np.ndarray | None, travel: Travel
) -> tuple[np.ndarray, np.ndarray] | None:
    """When tasks are towers that never move (EPT), every distance and wire charge :func:`pair_costs` can need, computed
    once: (N, N + 1) arrays whose column t is tower t and whose last column is an empty slot's (the origin, the last
    entity's wire, as :func:`pair_costs` sees it there), so that a step indexes them by the slots' towers (−1: empty).

    :return: the distances and the pair costs less the base cost, or None when tasks are not static towers
    """
    if towers is None or travel != "none":
        return None
    cells = np.vstack([entity_pos, np.zeros((1, 2))])
    dist = distances(entity_pos, cells, travel)
    return dist, dist * (0.5 * (wire[:, None] + np.append(wire, wire[-1])))
