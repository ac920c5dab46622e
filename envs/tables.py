"""Data of the environments: the JSON tables shipped with the package (``envs/data/*.json``, provenance in
``envs/data/PROVENANCE.md``) and the entity and task tables an env is built from."""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

DATA_DIR = Path(__file__).resolve().parent / "data"


@cache
def load_table(name: str) -> dict[str, Any]:
    """Load ``envs/data/<name>.json`` (cached; treat the result as read-only).

    :param name: one of ``almighty``, ``ept``, ``rbf``, ``mt``
    """
    path = DATA_DIR / f"{name}.json"
    if not path.exists():
        known = sorted(p.stem for p in DATA_DIR.glob("*.json"))
        raise ValueError(f"unknown data table {name!r}; known tables: {known}")
    with path.open() as f:
        return json.load(f)


@dataclass
class TaskTable:
    """Tasks that can arrive.

    :param rows: (T, 1 + K) array of ``[reward, demand_1..demand_K]``
    :param positions: optional (T, 2) integer cells used by ``arrival="reference"``
    :param towers: optional (T,) tower index of each task (EPT: the task is a tower that is then not an entity)
    """

    rows: np.ndarray
    positions: np.ndarray | None = None
    towers: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.rows = np.asarray(self.rows, dtype=np.float64)
        if self.rows.ndim != 2 or self.rows.shape[1] < 2:
            raise ValueError(f"task table must be (T, 1 + K) = [reward, demands...], got shape {self.rows.shape}")
        if len(self.rows) == 0:
            raise ValueError("the task table is empty: at least one task is needed")
        _check_values("task rewards", self.rows[:, 0], positive=True)
        _check_values("task demands", self.rows[:, 1:])
        if not (self.rows[:, 1:] > 0).any(1).all():
            raise ValueError(
                f"tasks {np.flatnonzero(~(self.rows[:, 1:] > 0).any(1)).tolist()} demand nothing: they would never open"
            )
        if self.positions is not None:
            self.positions = np.asarray(self.positions, dtype=np.int64).reshape(-1, 2)
            if len(self.positions) != len(self.rows):
                raise ValueError("task positions must have one row per task")
        if self.towers is not None:
            self.towers = np.asarray(self.towers, dtype=np.int64).reshape(-1)

    @property
    def n_resources(self) -> int:
        return self.rows.shape[1] - 1


@dataclass
class EntityTable:
    """Entities (robots, trucks, towers, workers).

    :param cost: (n,) base cost of using the entity once
    :param supply: (n, K) resources the entity brings
    :param positions: optional (n, 2) start cells
    :param wire_cost: optional (n,) per-unit-distance cost (EPT: pair cost = distance × mean wire cost of the pair)
    """

    cost: np.ndarray
    supply: np.ndarray
    positions: np.ndarray | None = None
    wire_cost: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.cost = np.asarray(self.cost, dtype=np.float64).reshape(-1)
        self.supply = np.asarray(self.supply, dtype=np.float64)
        if self.supply.ndim != 2 or len(self.supply) != len(self.cost):
            raise ValueError(f"entity supply must be (n, K) with n = {len(self.cost)}, got shape {self.supply.shape}")
        if len(self.cost) == 0:
            raise ValueError("the entity table is empty: at least one entity is needed")
        _check_values("entity costs", self.cost)
        _check_values("entity supplies", self.supply)
        if self.positions is not None:
            self.positions = np.asarray(self.positions, dtype=np.int64).reshape(-1, 2)
        if self.wire_cost is not None:
            self.wire_cost = np.asarray(self.wire_cost, dtype=np.float64).reshape(-1)
            _check_values("wire costs", self.wire_cost)
        for name in ("positions", "wire_cost"):  # a shorter column would be zero-padded: entities at (0, 0), free wires
            column = getattr(self, name)
            if column is not None and len(column) != len(self.cost):
                raise ValueError(f"entity {name} must have one row per entity ({len(self.cost)}), got {len(column)}")

    def __len__(self) -> int:
        return len(self.cost)

    @staticmethod
    def padded(column: np.ndarray | None, n_rows: int, width: int | None = None) -> np.ndarray:
        """``column`` (one value or row per entity) padded with zeros to ``n_rows`` rows; all zeros when it is None
        (then ``width`` values per row, or one)."""
        if column is None:
            return np.zeros((n_rows, width) if width else n_rows)
        out = np.zeros((n_rows, *column.shape[1:]), dtype=np.float64 if column.dtype != bool else bool)
        out[: len(column)] = column
        return out


def _check_values(what: str, values: np.ndarray, positive: bool = False) -> None:
    """Raise ``ValueError`` unless every value is finite and ≥ 0 (> 0 with ``positive``): costs, supplies, demands and
    rewards outside that range would put observations outside the observation space."""
    bad = ~np.isfinite(values) | ((values <= 0) if positive else (values < 0))
    if bad.any():
        where = np.argwhere(bad)[0].tolist()
        bound = "> 0" if positive else ">= 0"
        raise ValueError(f"{what} must be finite and {bound}; got {values[tuple(where)]} at {where}")


def clone(obj: Any, memo: dict[int, Any], shared: frozenset[str]) -> Any:
    """A deep copy of ``obj`` that shares the attributes named in ``shared``, copies arrays with ``ndarray.copy`` and
    random generators through their state (both much faster than :func:`copy.deepcopy`): planners clone envs by the
    thousand."""
    new = obj.__class__.__new__(obj.__class__)
    memo[id(obj)] = new
    for key, value in obj.__dict__.items():
        if key in shared:
            new.__dict__[key] = value
        elif isinstance(value, np.ndarray):
            new.__dict__[key] = value.copy()
        elif isinstance(value, np.random.Generator):
            rng = np.random.Generator(type(value.bit_generator)())
            rng.bit_generator.state = value.bit_generator.state
            new.__dict__[key] = rng
        else:
            new.__dict__[key] = copy.deepcopy(value, memo)
    return new
