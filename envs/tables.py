"""Data tables of the environments (``envs/data/*.json``; provenance in ``envs/data/PROVENANCE.md``)."""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path
from typing import Any

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

