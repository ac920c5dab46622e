"""Exact one-step allocation by mixed-integer programming, solved by HiGHS through scipy."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import Bounds, LinearConstraint, linprog, milp
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


#: Rounds of :func:`lagrangian_bound` by which :func:`cheapest_team` screens a task before its LP relaxation.
SCREEN_PASSES = 3

# Nodes of :func:`cheapest_team`'s search before :func:`max_profit_team` hands a task to HiGHS: on the DAgger labels of
# trained RBF, MT and EPT models all tasks but about one in 600 finish within it (docs/benchmarks.md, "Exact teams by
# branch and bound").
TEAM_NODE_LIMIT = 5000
# The search recurses once per group of identical candidates; a task with more groups goes to HiGHS (Python's recursion
# limit is 1,000 frames, and such a task is far past what the node limit lets the search finish).
TEAM_MAX_GROUPS = 500


def cheapest_team(
    cost: np.ndarray, useful: np.ndarray, demand: np.ndarray, budget: float, node_limit: int = TEAM_NODE_LIMIT
) -> np.ndarray | None:
    """The cheapest team that covers one task, among teams cheaper than ``budget``, by depth-first branch and bound:

    minimise Σ_i c_i x_i  subject to  Σ_i u_ik x_i ≥ d_k for every resource k, x binary, Σ_i c_i x_i < budget.

    Entities with c_i ≤ 0 join any team (they lower its cost). The others are grouped by identical (c_i, u_i) and the
    search branches on how many of a group join, most first, in the order of their reduced costs c_i − λ·u_i under the
    duals λ of the LP relaxation. Before the LP, up to :data:`SCREEN_PASSES` rounds of :func:`lagrangian_bound` from
    λ = 0 return "no team" where they already bound every team's cost at ``budget`` or more (the LP's bound is at least
    as high, so the result is the same; this spares four in five LPs of DAgger's labels). A node is cut by the
    Lagrangian bound λ·r + Σ min(0, c − λ·u) over the groups not yet decided (r: the demand still uncovered), by r_k
    times the lowest cost per unit of resource k among them, or when they cannot cover r. The result is exact; of
    equally cheap teams the first found is kept.

    :param cost: (n,) the entities' costs for the task
    :param useful: (n, K) what each entity contributes to each resource, min(supply, demand) in the MILP's formulation
    :param demand: (K,) the task's demand
    :param budget: only teams strictly cheaper than this count (the task's reward: a team worth keeping)
    :param node_limit: search nodes before giving up
    :return: (n,) bool the team, an all-False mask where no team is cheaper than ``budget``, or None where the search
        reached ``node_limit`` first (or the LP relaxation failed numerically, or the candidates form more than
        :data:`TEAM_MAX_GROUPS` groups)
    """
    n = len(cost)
    team = cost <= 0
    deficit = demand - useful[team].sum(0)
    spent0 = float(cost[team].sum())
    tol = 1e-9 * np.maximum(1.0, demand)  # float sums of decayed demands: a cover short by rounding alone is a cover
    need = deficit > tol
    if not need.any():
        return team if spent0 < budget else np.zeros(n, bool)
    r0, eps = deficit[need], tol[need]
    u = np.minimum(useful[:, need], r0)  # more of a resource than is missing is worth nothing
    cand = np.flatnonzero(~team & (u > 0).any(1))
    if len(cand) == 0 or (u[cand].sum(0) < r0 - eps).any():
        return np.zeros(n, bool)
    r0 = r0 - eps  # the search covers r0 − eps, so that its bounds hold for the teams it accepts
    lam, ones = np.zeros(len(r0)), np.ones(len(cand))
    for _ in range(SCREEN_PASSES):  # most tasks are not worth covering, and a Lagrangian bound shows it without the LP
        bound, lam = lagrangian_bound(cost[cand], u[cand], ones, r0, lam)
        if spent0 + bound >= budget:
            return np.zeros(n, bool)
    keys, inverse, counts = np.unique(np.column_stack([cost[cand], u[cand]]), axis=0, return_inverse=True, return_counts=True)
    if len(keys) > TEAM_MAX_GROUPS:
        return None
    c, ug = keys[:, 0], keys[:, 1:]
    lp = linprog(c, A_ub=-ug.T, b_ub=-r0, bounds=np.column_stack([np.zeros(len(c)), counts]), method="highs")
    if lp.status == 2 or (lp.status == 0 and spent0 + lp.fun >= budget):  # the LP bounds every team's cost from below
        return np.zeros(n, bool)
    if lp.status != 0:  # a numerical failure of the LP: no bound to search with
        return None
    lam = np.maximum(-lp.ineqlin.marginals, 0.0)
    rc = c - ug @ lam
    order = np.lexsort((c, rc))  # the branching order: by reduced cost, then cost
    found = _TeamSearch(c[order], ug[order], counts[order], rc[order], lam, node_limit).run(r0, budget - spent0)
    if found is None:
        return None
    if found:
        wanted = np.zeros(len(c), np.int64)
        wanted[order] = found  # per group of ``keys``
        for pos, i in enumerate(cand):  # each group's count from its lowest-index entities
            g = inverse.flat[pos]
            if wanted[g] > 0:
                team[i] = True
                wanted[g] -= 1
        return team
    return np.zeros(n, bool)


def lagrangian_bound(
    cost: np.ndarray, useful: np.ndarray, counts: np.ndarray, r: np.ndarray, start: np.ndarray
) -> tuple[float, np.ndarray]:
    """A lower bound on the cost of covering ``r`` with up to ``counts[h]`` copies of groups (c_h, u_h): the Lagrangian
    bound λ·r + Σ n_h min(0, c_h − λ·u_h) with u capped at r (any λ ≥ 0 gives one), λ raised from ``start`` by one exact
    line search along each λ_k in turn. :return: the bound and λ"""
    u = np.minimum(useful, r)
    lam = start.copy()
    by_resource = u.T.copy()  # contiguous rows: this runs at every node of a team search, on a few dozen groups
    for k, uk in enumerate(by_resource):
        pos = uk > 0
        # Along λ_k the bound's slope is r_k − Σ n_h u_hk over the groups past their breakpoint, where c_h − λ·u_h turns
        # negative: its maximum is the first breakpoint at which those groups supply r_k.
        if pos.all():  # the common case, spared the masked copies
            brk, supplied = (cost - u @ lam + uk * lam[k]) / uk, counts * uk
        elif pos.any():
            brk, supplied = (cost - u @ lam + uk * lam[k])[pos] / uk[pos], counts[pos] * uk[pos]
        else:
            continue
        srt = brk.argsort()
        j = int(supplied[srt].cumsum().searchsorted(r[k]))
        if j < len(srt):  # else the groups cannot supply r_k (no cover exists; the callers cut such a node)
            lam[k] = max(float(brk[srt[j]]), 0.0)
    return float(lam @ r + (np.minimum(0.0, cost - u @ lam) * counts).sum()), lam


class _TeamSearch:
    """:func:`cheapest_team`'s depth-first search over the groups, in their branching order, with plain Python floats
    (K is a handful: numpy's per-call cost would dominate a node)."""

    def __init__(
        self,
        cost: np.ndarray,
        useful: np.ndarray,
        counts: np.ndarray,
        reduced: np.ndarray,
        lam: np.ndarray,
        node_limit: int,
    ) -> None:
        G, K = useful.shape
        # Lagrangian bound over groups g.. : Σ min(0, c − λ·u) × count
        self.neg = np.append(np.cumsum((np.minimum(reduced, 0.0) * counts)[::-1])[::-1], 0.0).tolist()
        with np.errstate(divide="ignore"):
            per_unit = np.where(useful > 0, cost[:, None] / np.where(useful > 0, useful, 1.0), np.inf)
        self.low_per_unit = np.vstack([np.minimum.accumulate(per_unit[::-1], 0)[::-1], np.full((1, K), np.inf)]).tolist()
        self.supply_left = np.vstack([np.cumsum((useful * counts[:, None])[::-1], 0)[::-1], np.zeros((1, K))]).tolist()
        self.cost, self.useful, self.counts = cost.tolist(), useful.tolist(), counts.tolist()
        self.c_np, self.u_np, self.n_np, self.lam_np = cost, useful, counts, lam
        self.lam, self.ks, self.G = lam.tolist(), range(K), G
        self.node_limit, self.nodes = node_limit, 0
        self.take = [0] * G
        self.best_cost, self.best_take = 0.0, list[int]()

    def _dual_bound(self, g: int, r: list[float], start: np.ndarray) -> tuple[float, np.ndarray]:
        """:func:`lagrangian_bound` of groups g.. with ``r`` uncovered, from the parent's λ"""
        return lagrangian_bound(self.c_np[g:], self.u_np[g:], self.n_np[g:], np.asarray(r), start)

    def run(self, r0: np.ndarray, budget: float) -> list[int] | None:
        """:return: the count taken of each group (empty: no team cheaper than ``budget``), None at the node limit"""
        self.best_cost, self.best_take = budget, []
        return self.best_take if self._search(0, r0.tolist(), 0.0, self.lam_np) else None

    def _search(self, g: int, r: list[float], spent: float, lam: np.ndarray) -> bool:
        """Branch on group ``g`` with ``r`` still uncovered; False once the node limit is reached."""
        self.nodes += 1
        if self.nodes > self.node_limit:
            return False
        if g == self.G:
            return True
        ks = self.ks
        bound = self.neg[g] + sum(self.lam[k] * r[k] for k in ks)
        for k in ks:
            if r[k] > 0:
                if self.supply_left[g][k] < r[k]:
                    return True
                bound = max(bound, r[k] * self.low_per_unit[g][k])
        if spent + bound >= self.best_cost:
            return True
        dual, lam = self._dual_bound(g, r, lam)
        if spent + dual >= self.best_cost:
            return True
        cg, ug = self.cost[g], self.useful[g]
        most = max((-int(-r[k] // ug[k]) for k in ks if r[k] > 0 and ug[k] > 0), default=0)  # more copies add only cost
        for t in range(min(most, self.counts[g]), -1, -1):
            s = spent + t * cg
            if s >= self.best_cost:
                continue
            left = [max(r[k] - t * ug[k], 0.0) for k in ks]
            self.take[g] = t
            if not any(left):
                self.best_cost, self.best_take = s, self.take[: g + 1] + [0] * (self.G - g - 1)
            elif not self._search(g + 1, left, s, lam):
                return False
        self.take[g] = 0
        return True


def max_profit_team(
    supply: np.ndarray,
    demand: np.ndarray,
    reward: float,
    cost: np.ndarray,
    time_limit: float = 10.0,
    node_limit: int | None = None,
    team_node_limit: int = TEAM_NODE_LIMIT,
) -> np.ndarray:
    """The most profitable team of one task, :func:`max_profit_cover` with one task: :func:`cheapest_team` within
    ``team_node_limit`` nodes, else HiGHS with ``time_limit`` and ``node_limit``.

    :param supply: (n, K) supplies of the candidates
    :param demand: (K,) the task's demand
    :param reward: the task's reward
    :param cost: (n,) the candidates' costs for the task
    :return: (n,) bool the team (all False: no team pays)
    """
    team = cheapest_team(cost, np.minimum(supply, demand), demand, reward, team_node_limit)
    if team is not None:
        return team
    x, _, _ = max_profit_cover(
        supply, demand[None], np.array([reward]), cost[:, None], time_limit=time_limit, node_limit=node_limit
    )
    return x[:, 0]


class MILPAllocator(Allocator):
    """The exact allocation of the current step among free entities and open tasks (:func:`max_profit_cover` over
    every pair). It is the per-step upper reference: it ignores travel time, decay and future tasks.

    :param time_limit: HiGHS time limit per solve (seconds); the best allocation found is used when it is reached, so
        where it binds the allocation depends on the machine's speed and load
    :param mip_rel_gap: relative optimality gap at which HiGHS stops
    :param node_limit: HiGHS node limit per solve (None: none); the best allocation found is used when it is reached.
        A stop by work: with ``time_limit=float("inf")`` the allocations are the same on any machine and under any
        load (the experiments' reference, :func:`reference`)

    :attr:`gaps` holds each solve's relative MIP gap (0 where it was proven optimal), :meth:`gap_summary` their summary.
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
        self.gaps: list[float] = []

    @classmethod
    def reference(cls, node_limit: int) -> MILPAllocator:
        """The per-step MILP stopped by work only (``node_limit`` HiGHS nodes per solve, no clock): the same allocations
        on every machine and under any load, so the experiments' MILP figures repeat."""
        return cls(time_limit=float("inf"), node_limit=node_limit)

    def gap_summary(self) -> dict[str, float]:
        """Over the solves so far: their number, the share stopped short of proven optimality, and the mean and largest
        relative MIP gap (how far from optimal the allocations may be)."""
        gaps = np.asarray(self.gaps, dtype=float)
        if gaps.size == 0:
            return self.pooled_gap_summary([])
        return {"solves": float(gaps.size), "stopped": float((gaps > self.mip_rel_gap).mean()),
                "mean_gap": float(gaps.mean()), "max_gap": float(gaps.max())}  # fmt: skip

    @staticmethod
    def pooled_gap_summary(summaries: list[dict[str, float]]) -> dict[str, float]:
        """:meth:`gap_summary` of the solves of several allocators (or runs) together."""
        solves = sum(s["solves"] for s in summaries)
        if not solves:
            return {"solves": 0.0, "stopped": 0.0, "mean_gap": 0.0, "max_gap": 0.0}
        return {"solves": solves, "stopped": sum(s["stopped"] * s["solves"] for s in summaries) / solves,
                "mean_gap": sum(s["mean_gap"] * s["solves"] for s in summaries) / solves,
                "max_gap": max(s["max_gap"] for s in summaries if s["solves"])}  # fmt: skip

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
        gap = self.last.mip_gap
        self.gaps.append(float(gap) if gap is not None and np.isfinite(gap) else (0.0 if res.status == 0 else 1.0))
        return action
