"""Data tables of the environments (``envs/data/*.json``; provenance in ``envs/data/PROVENANCE.md``)."""

from __future__ import annotations

import json
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


def table_array(name: str, key: str) -> np.ndarray:
    """One array of a data table, e.g. ``table_array("rbf", "entities_train_100")``."""
    data = load_table(name)
    if key not in data:
        arrays = sorted(k for k, v in data.items() if isinstance(v, list))
        raise ValueError(f"table {name!r} has no array {key!r}; arrays: {arrays}")
    return np.asarray(data[key], dtype=np.float64)
