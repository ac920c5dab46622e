"""Checks of an environment's configuration and of the actions it is given: bad input gets a ``ValueError`` that names
what is wrong."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from envs.tables import EntityTable, TaskTable

#: Tolerance used when comparing supplied resources to demands.
EPS = 1e-6


#: Numeric settings: (lowest, highest, whether the lowest is excluded, whether the highest is excluded).
RANGES: dict[str, tuple[float, float, bool, bool]] = {
    "max_tasks": (1, math.inf, False, True),
    "arrival_period": (1, math.inf, False, True),
    "reward_scale": (0.0, math.inf, True, True),
    "travel_cost": (0.0, math.inf, False, True),
    "demand_noise": (0.0, 1.0, False, True),
    "decay": (0.0, 1.0, True, False),
    "decay_after": (0, math.inf, False, True),
}


def check_range(name: str, value: float, low: float, high: float, low_open: bool, high_open: bool) -> None:
    """Raise ``ValueError`` naming ``name`` unless ``value`` is a number in the interval."""
    ok = isinstance(value, int | float) and not math.isnan(value)
    ok = ok and (value > low if low_open else value >= low) and (value < high if high_open else value <= high)
    if not ok:
        interval = f"{'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
        raise ValueError(f"{name} must lie in {interval}, got {value!r}")


def check_config(entities: EntityTable, tasks: TaskTable, render_modes: Sequence[str], **settings: Any) -> None:
    """Raise ``ValueError`` for a configuration the env cannot run, naming the setting (see ``TaskAllocEnv.__init__``
    for their meanings)."""
    s = settings
    for name, bounds in RANGES.items():
        check_range(name, s[name], *bounds)
    if isinstance(s["max_entities"], bool) or not isinstance(s["max_entities"], int | np.integer):
        raise ValueError(f"max_entities must be an integer, got {s['max_entities']!r}")
    if s["max_entities"] < len(entities):
        raise ValueError(f"max_entities={s['max_entities']} is smaller than the {len(entities)} entities of the table")
    if s["grid_size"] is not None:
        check_range("grid_size", s["grid_size"], 1, math.inf, False, True)
    if s["bid_max"] is not None:
        check_range("bid_max", s["bid_max"], 0.0, math.inf, True, True)
    if tasks.n_resources != entities.supply.shape[1]:
        raise ValueError(
            f"tasks demand {tasks.n_resources} resources but entities supply {entities.supply.shape[1]}: K must match"
        )
    for name, choices in (("travel", ("none", "manhattan", "chebyshev")), ("arrival", ("random", "reference", "static"))):
        if s[name] not in choices:
            raise ValueError(f"{name} must be one of {list(choices)}, got {s[name]!r}")
    low, high = s["arrival_count"]
    if low < 0 or high < low:
        raise ValueError(f"arrival_count must be an increasing (low, high) pair, got {s['arrival_count']}")
    if s["render_mode"] is not None and s["render_mode"] not in render_modes:
        raise ValueError(f"render_mode must be one of {list(render_modes)}, got {s['render_mode']!r}")
    check_grid(entities, tasks, s["travel"], s["grid_size"])
    check_bounds(entities, tasks, s)


def check_bounds(entities: EntityTable, tasks: TaskTable, s: dict[str, Any]) -> None:
    """Raise ``ValueError`` where the settings would give observations above the observation space's bound
    (:data:`~envs.layout.FEATURE_HIGH`): scaled task rewards and demands, and the pair costs of the farthest trip."""
    from envs.layout import FEATURE_HIGH

    largest = {
        "task reward × reward_scale × (1 + demand_noise)": float(tasks.rows.max())
        * s["reward_scale"]
        * (1 + s["demand_noise"]),
        "entity cost + travel_cost × the grid's largest distance": float(entities.cost.max())
        + s["travel_cost"] * 2 * max((s["grid_size"] or 1) - 1, 0),
        "bid_max": s["bid_max"] or 0.0,
    }
    for what, value in largest.items():
        if not value <= FEATURE_HIGH:
            raise ValueError(
                f"these settings give observations up to {value:.3g} ({what}), above the observation space's bound "
                f"{FEATURE_HIGH:g}: lower reward_scale, travel_cost or the table's values"
            )


def check_grid(entities: EntityTable, tasks: TaskTable, travel: str, grid_size: int | None) -> None:
    """Raise ``ValueError`` unless travel has positions on a grid and every position lies on it."""
    if travel != "none" and (entities.positions is None or grid_size is None):
        raise ValueError("travel needs entity positions and a grid_size")
    for what, cells in (("entity", entities.positions), ("task", tasks.positions)):
        if cells is not None and grid_size is not None and ((cells < 0) | (cells >= grid_size)).any():
            raise ValueError(f"{what} positions must lie on the grid, in [0, {grid_size - 1}]")


def check_action(action: Any, n_entities: int, n_tasks: int) -> np.ndarray:
    """The action as an (N,) int64 array, or ``ValueError`` naming what is wrong: anything but N integers (or
    integral floats) in [0, M] is refused, M meaning "unassigned".

    :param n_entities: N, the padded entity count; :param n_tasks: M, the number of task slots
    """
    N, M = n_entities, n_tasks
    if type(action) is np.ndarray and action.dtype == np.int64 and action.shape == (N,):  # fast path
        if action.view(np.uint64).max() > M:  # one pass: a negative value reads as a huge unsigned one
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
