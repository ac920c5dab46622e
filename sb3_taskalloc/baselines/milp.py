"""Exact one-step allocation by mixed-integer programming, solved by HiGHS through scipy."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import Bounds, LinearConstraint, milp
from scipy.sparse import coo_matrix, hstack

from sb3_taskalloc.baselines.base import Allocator
from sb3_taskalloc.common.utils import check_counts


@contextmanager
def _highs_stdout_silenced() -> Iterator[None]:
    """Point file descriptor 1 at the null device for the duration of a solve.

    HiGHS's MIP solver prints ``HighsMipSolverData::transformNewIntegerFeasibleSolution tmpSolver.run();`` straight to the
    C-level stdout on some solves, whatever its output options say; in training with ``select_search_method='exact'``
    that is hundreds of lines a minute. Python's own buffer is flushed first, so nothing printed before is lost; what
    another thread writes to descriptor 1 during the solve is dropped with it (the package prints nothing meanwhile).
    """
    fd = 1
    if sys.stdout is not None:
        sys.stdout.flush()
    try:
        saved = os.dup(fd)
    except OSError:  # no descriptor 1 to silence (a detached process)
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), fd)
            try:
                yield
            finally:
                os.dup2(saved, fd)
    finally:
        os.close(saved)


@dataclass
class MILPSolution:
    """Outcome of the last solve: the allocation, its objective, HiGHS's status and the relative MIP gap."""

    action: np.ndarray
    objective: float
    status: int
    message: str
    mip_gap: float | None
    seconds: float


def max_profit_cover(
    supply: np.ndarray,
    demand: np.ndarray,
    reward: np.ndarray,
    cost: np.ndarray,
    allowed: np.ndarray | None = None,
    time_limit: float = 10.0,
    mip_rel_gap: float = 1e-6,
    node_limit: int | None = None,
) -> tuple[np.ndarray, np.ndarray, Any]:
    """The most profitable set of covered tasks and their teams, among the ``allowed`` entity-task pairs:

    maximise Σ_j R_j y_j − Σ_ij c_ij x_ij  subject to  Σ_j x_ij ≤ 1 (each entity serves at most one task),
    Σ_i min(s_ik, d_jk) x_ij ≥ d_jk y_j for every resource k (a task pays only if covered), x_ij ≤ y_j,
    x, y binary, x_ij = 0 where a pair is not allowed (it has no variable).

    :param supply: (n, K) supplies of the entities
    :param demand: (m, K) demands of the tasks
    :param reward: (m,) rewards of the tasks
    :param cost: (n, m) pair costs
    :param allowed: (n, m) bool pairs that may be assigned (None: all)
    :param time_limit: HiGHS time limit (seconds); the best allocation found is used when it is reached
    :param mip_rel_gap: relative optimality gap at which HiGHS stops
    :param node_limit: HiGHS branch-and-bound node limit (None: none); the best allocation found is used when it is
        reached. Unlike the time limit it bounds the search by work, so the result does not depend on the machine's
        speed or load (HiGHS's branch and bound is deterministic given its options)
    :return: x (n, m) bool teams of the covered tasks, y (m,) bool covered tasks, and scipy's result
    """
    n, m, K = len(supply), len(demand), supply.shape[1]
    ents, tasks = np.nonzero(np.ones((n, m), bool) if allowed is None else allowed)  # row-major: pair p = (ents[p], tasks[p])
    P = len(ents)
    # Variables: x (one per allowed pair), then y (m). milp minimises, so negate the profit.
    c = np.concatenate([cost[ents, tasks], -reward])
    cols_x = np.arange(P)
    # Σ_j x_ij ≤ 1
    one_task = coo_matrix((np.ones(P), (ents, cols_x)), shape=(n, P + m))
    # Σ_i min(s_ik, d_jk) x_ij − d_jk y_j ≥ 0, one row per (j, k)
    useful = np.minimum(supply[ents], demand[tasks])  # (P, K)
    rows = tasks[:, None] * K + np.arange(K)[None, :]
    cover_x = coo_matrix((useful.ravel(), (rows.ravel(), np.repeat(cols_x, K))), shape=(m * K, P))
    cover_y = coo_matrix((-demand.ravel(), (np.arange(m * K), np.repeat(np.arange(m), K))), shape=(m * K, m))
    cover = hstack([cover_x, cover_y])
    # x_ij − y_j ≤ 0
    link = hstack([coo_matrix((np.ones(P), (cols_x, cols_x)), shape=(P, P)),
                   coo_matrix((-np.ones(P), (cols_x, tasks)), shape=(P, m))])  # fmt: skip
    constraints = [
        LinearConstraint(one_task.tocsr(), -np.inf, 1.0),
        LinearConstraint(cover.tocsr(), 0.0, np.inf),
        LinearConstraint(link.tocsr(), -np.inf, 0.0),
    ]
    with _highs_stdout_silenced():
        res = milp(
            c,
            constraints=constraints,
            integrality=np.ones(P + m),
            bounds=Bounds(0, 1),
            options={"time_limit": time_limit, "mip_rel_gap": mip_rel_gap, "node_limit": node_limit},
        )
    x = np.zeros((n, m), bool)
    y = np.zeros(m, bool)
    if res.x is not None:
        y = np.round(res.x[P:]).astype(bool)
        chosen = np.round(res.x[:P]).astype(bool) & y[tasks]
        x[ents[chosen], tasks[chosen]] = True
    return x, y, res


class MILPAllocator(Allocator):
    """The exact allocation of the current step among free entities and open tasks (:func:`max_profit_cover` over
    every pair). It is the per-step upper reference: it ignores travel time, decay and future tasks.

    :param time_limit: HiGHS time limit per solve (seconds); the best allocation found is used when it is reached, so
        where it binds the allocation depends on the machine's speed and load
    :param mip_rel_gap: relative optimality gap at which HiGHS stops
    :param node_limit: HiGHS node limit per solve (None: none); the best allocation found is used when it is reached.
        A stop by work: with ``time_limit=float("inf")`` the allocations are the same on any machine
    """

    def __init__(self, time_limit: float = 10.0, mip_rel_gap: float = 1e-6, node_limit: int | None = None) -> None:
        if not (isinstance(time_limit, int | float) and time_limit > 0):  # NaN fails the comparison too
            raise ValueError(f"time_limit must be a number of seconds > 0 (inf: no limit), got {time_limit!r}")
        if not (isinstance(mip_rel_gap, int | float) and 0 <= mip_rel_gap < 1):
            raise ValueError(f"mip_rel_gap must lie in [0, 1), got {mip_rel_gap!r}")
        if node_limit is not None:
            check_counts({"node_limit": node_limit})
        self.time_limit = time_limit
        self.mip_rel_gap = mip_rel_gap
        self.node_limit = node_limit
        self.last: MILPSolution | None = None

    def allocate(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        import time

        free = np.flatnonzero(obs["entity_mask"].astype(bool))
        open_ = np.flatnonzero(obs["task_mask"].astype(bool))
        N, M = len(obs["entity_mask"]), len(obs["task_mask"])
        action = np.full(N, M, dtype=np.int64)
        if len(free) == 0 or len(open_) == 0:
            self.last = MILPSolution(action, 0.0, 0, "nothing to allocate", 0.0, 0.0)
            return action
        supply = obs["entity_supply"][free].astype(np.float64)  # (n, K)
        demand = obs["task_demand"][open_].astype(np.float64)  # (m, K)
        reward = obs["task_reward"][open_].astype(np.float64)
        cost = obs["pair_cost"][np.ix_(free, open_)].astype(np.float64)  # (n, m)
        t0 = time.perf_counter()
        x, y, res = max_profit_cover(
            supply, demand, reward, cost, time_limit=self.time_limit, mip_rel_gap=self.mip_rel_gap, node_limit=self.node_limit
        )
        seconds = time.perf_counter() - t0
        objective = 0.0
        if res.x is not None:
            ents, tasks = np.nonzero(x)
            action[free[ents]] = open_[tasks]
            objective = float(reward @ y - (cost * x).sum())
        self.last = MILPSolution(action, objective, int(res.status), str(res.message), getattr(res, "mip_gap", None), seconds)
        return action
