"""Checks of an environment's configuration and of the actions it is given: bad input gets a ``ValueError`` that names
what is wrong."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from envs.tables import EntityTable, TaskTable

#: Tolerance used when comparing supplied resources to demands.
EPS = 1e-6


def check_config(
    entities: EntityTable,
    tasks: TaskTable,
    max_entities: int,
    max_tasks: int,
    travel: str,
    arrival: str,
    arrival_count: tuple[int, int],
    decay: float,
    grid_size: int | None,
    render_mode: str | None,
    render_modes: Sequence[str],
) -> None:
    """Raise ``ValueError`` for a configuration the env cannot run (see ``TaskAllocEnv.__init__`` for the meanings)."""
    n = len(entities)
    if max_entities < n:
        raise ValueError(f"max_entities={max_entities} is smaller than the {n} entities of the table")
    if max_tasks < 1:
        raise ValueError(f"max_tasks must be >= 1, got {max_tasks}")
    if tasks.n_resources != entities.supply.shape[1]:
        raise ValueError(
            f"tasks demand {tasks.n_resources} resources but entities supply {entities.supply.shape[1]}: K must match"
        )
    if travel not in ("none", "manhattan", "chebyshev"):
        raise ValueError(f"travel must be 'none', 'manhattan' or 'chebyshev', got {travel!r}")
    if arrival not in ("random", "reference", "static"):
        raise ValueError(f"arrival must be 'random', 'reference' or 'static', got {arrival!r}")
    if arrival_count[0] < 0 or arrival_count[1] < arrival_count[0]:
        raise ValueError(f"arrival_count must be an increasing (low, high) pair, got {arrival_count}")
    if not 0.0 < decay <= 1.0:
        raise ValueError(f"decay must lie in (0, 1], got {decay}")
    if render_mode is not None and render_mode not in render_modes:
        raise ValueError(f"render_mode must be one of {list(render_modes)}, got {render_mode!r}")
    if travel != "none" and (entities.positions is None or grid_size is None):
        raise ValueError("travel needs entity positions and a grid_size")


def check_action(action: Any, n_entities: int, n_tasks: int) -> np.ndarray:
    """The action as an (N,) int64 array, or ``ValueError`` naming what is wrong: anything but N integers (or
    integral floats) in [0, M] is refused, M meaning "unassigned".

    :param n_entities: N, the padded entity count; :param n_tasks: M, the number of task slots
    """
    N, M = n_entities, n_tasks
    if type(action) is np.ndarray and action.dtype == np.int64 and action.shape == (N,):  # fast path
        if action.min() < 0 or action.max() > M:
            raise ValueError(
                f"action values must lie in [0, {M}] (M = {M} means 'unassigned'), got [{action.min()}, {action.max()}]"
            )
        return action
    a = np.asarray(action)
    if a.shape != (N,):
        raise ValueError(f"action must have shape ({N},) (one task slot per entity), got shape {a.shape}")
    if a.dtype.kind == "f":
        if not np.all(np.isfinite(a)):
            raise ValueError("action contains NaN or infinite values; expected integers in [0, max_tasks]")
        if not np.all(a == np.round(a)):
            raise ValueError("action contains non-integer values; expected integers in [0, max_tasks]")
        a = a.astype(np.int64)
    elif a.dtype.kind not in "iu":
        raise ValueError(f"action must be an integer array (one task slot per entity), got dtype {a.dtype}")
    lo, hi = a.min(), a.max()
    if lo < 0 or hi > M:
        raise ValueError(f"action values must lie in [0, {M}] (M = {M} means 'unassigned'), got [{lo}, {hi}]")
    return a.astype(np.int64, copy=False)


def check_bids(bids: Any, n_entities: int, max_entities: int, bid_max: float) -> np.ndarray:
    """The bids as a float array of ``n_entities`` or ``max_entities`` values in [0, ``bid_max``], or ``ValueError``."""
    b = np.asarray(bids, dtype=np.float64).reshape(-1)
    if b.shape[0] not in (n_entities, max_entities):
        raise ValueError(f"bids must have shape ({n_entities},) or ({max_entities},), got {np.shape(bids)}")
    if not np.all(np.isfinite(b)) or b.min(initial=0.0) < 0 or b.max(initial=0.0) > bid_max + EPS:
        raise ValueError(f"bids must be finite and lie in [0, bid_max={bid_max}]")
    return b
