"""Arrival processes: which rows of the task table arrive into the free slots, and where.

The env asks its process at reset and every ``arrival_period`` steps (:attr:`Arrival.periodic`), places what it
returns, and ends an episode once the process is :meth:`~Arrival.exhausted` and every slot is empty.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np


class ArrivalState(NamedTuple):
    """What an arrival process may see of the env."""

    rng: np.random.Generator
    free_slots: int  # empty task slots
    task_entities: np.ndarray  # entities that are tasks now (EPT's towers at peak demand)
    alive: np.ndarray  # (N,) bool: entities present and not used up


class Arrivals(NamedTuple):
    """Rows of the task table that arrive, at ``cells`` (None: their table positions, or their towers' cells)."""

    rows: np.ndarray
    cells: np.ndarray | None = None


class Arrival:
    """Base process: nothing arrives; subclasses override :meth:`draw`."""

    #: Whether the process is asked again every ``arrival_period`` steps (else only at reset).
    periodic = True

    def reset(self) -> None:
        """Start a new episode."""

    def draw(self, state: ArrivalState) -> Arrivals:
        return Arrivals(np.zeros(0, dtype=np.int64))

    def exhausted(self) -> bool:
        """Whether nothing more can ever arrive in this episode."""
        return False


class RandomArrival(Arrival):
    """The paper's process: ``count`` tasks (uniform in an inclusive range) drawn from the table at random cells.

    :param n_rows: rows of the task table
    :param count: inclusive (low, high) range of tasks per arrival
    :param grid_size: side of the grid of the cells (None: cell 0)
    """

    def __init__(self, n_rows: int, count: tuple[int, int], grid_size: int | None) -> None:
        self.n_rows, self.count, self.grid_size = n_rows, count, grid_size

    def draw(self, state: ArrivalState) -> Arrivals:
        count = min(int(state.rng.integers(self.count[0], self.count[1] + 1)), state.free_slots)
        u = state.rng.random(3 * count)  # one draw for the rows and the cells
        rows = (u[:count] * self.n_rows).astype(np.int64)
        cells = (u[count:] * (self.grid_size or 1)).astype(np.int64).reshape(count, 2)
        return Arrivals(rows, cells)


class TowerPeakArrival(Arrival):
    """EPT: ``count`` towers that are not tasks already reach their peak demand and become tasks; at least one tower
    stays a supplier. The task table has one row per tower.

    :param count: inclusive (low, high) range of towers per arrival
    """

    def __init__(self, count: tuple[int, int]) -> None:
        self.count = count

    def draw(self, state: ArrivalState) -> Arrivals:
        count = min(int(state.rng.integers(self.count[0], self.count[1] + 1)), state.free_slots)
        eligible = state.alive.copy()
        eligible[state.task_entities] = False
        candidates = np.flatnonzero(eligible)
        count = min(count, max(len(candidates) - 1, 0))
        return Arrivals(candidates[np.argsort(state.rng.random(len(candidates)))[:count]])


class ReferenceArrival(Arrival):
    """The published fixed schedule: the table's rows in order, refilling the empty slots. With towers, a tower that is
    a task already waits (and the rows after it) for the next refill.

    :param n_rows: rows of the task table
    :param towers: (n_rows,) tower of each row, or None
    """

    def __init__(self, n_rows: int, towers: np.ndarray | None = None) -> None:
        self.n_rows, self.towers = n_rows, towers
        self.next_row = 0

    def reset(self) -> None:
        self.next_row = 0

    def draw(self, state: ArrivalState) -> Arrivals:
        rows = np.arange(self.next_row, min(self.next_row + state.free_slots, self.n_rows))
        if self.towers is not None:
            busy = set(state.task_entities.tolist())
            keep = []
            for r in rows:
                if int(self.towers[r]) in busy:
                    break
                busy.add(int(self.towers[r]))
                keep.append(r)
            rows = np.asarray(keep, dtype=np.int64)
        self.next_row += len(rows)
        return Arrivals(rows)

    def exhausted(self) -> bool:
        return self.next_row >= self.n_rows


class StaticArrival(Arrival):
    """The whole table (as many rows as there are slots) at reset, nothing later.

    :param n_rows: rows of the task table
    """

    periodic = False

    def __init__(self, n_rows: int) -> None:
        self.n_rows = n_rows

    def draw(self, state: ArrivalState) -> Arrivals:
        return Arrivals(np.arange(min(self.n_rows, state.free_slots)))

    def exhausted(self) -> bool:
        return True


def make_arrival(
    kind: Literal["random", "reference", "static"],
    n_rows: int,
    towers: np.ndarray | None,
    count: tuple[int, int],
    grid_size: int | None,
) -> Arrival:
    """The process named ``kind`` for a task table of ``n_rows`` rows (``towers``: the tower of each row, EPT)."""
    if kind == "static":
        return StaticArrival(n_rows)
    if kind == "reference":
        return ReferenceArrival(n_rows, towers)
    if towers is not None:
        return TowerPeakArrival(count)
    return RandomArrival(n_rows, count, grid_size)
