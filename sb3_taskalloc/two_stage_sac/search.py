"""Searches over the decisions of the two stages, scored by the step's exact profit (:func:`.select_stage.task_profit`,
:func:`.select_stage.round_profit`): sampled pre-assignments, sampled teams and the exact most profitable covers. The
decoding strategies (:mod:`.decoding`) use them at decision time, the select stage's search term and DAgger as teachers.
"""

from __future__ import annotations

import heapq
from typing import NamedTuple

import numpy as np
import torch as th

from sb3_taskalloc.common.distributions import MaskedCategorical
from sb3_taskalloc.common.torch_layers import ObsView, PointerHead
from sb3_taskalloc.two_stage_sac.select_stage import SelectState, decode_round, round_profit, task_profit

#: The observation fields that the select stage reads besides the entity features of its embeddings (:mod:`.select_stage`).
SELECT_FIELDS = ("supply", "demand", "reward", "pair_cost", "task_mask")


def select_copies(view: ObsView, copies: int) -> ObsView:
    """``copies`` consecutive copies of each row of ``view`` for the select stage's decoding with the rows' entity
    embeddings given: the fields it does not read (:data:`SELECT_FIELDS`) stay behind, empty, so the copies cost what
    the decoding needs (the pair basis alone is M × 5 numbers per entity)."""
    rows = view.reward.shape[0] * copies
    return ObsView(
        *(
            x.repeat_interleave(copies, 0) if name in SELECT_FIELDS else x.new_empty((rows, *[0] * (x.dim() - 1)))
            for name, x in zip(ObsView._fields, view, strict=True)
        )
    )


class SelectSearchResult(NamedTuple):
    """Each task's best team of a select-stage search (:func:`select_search`)."""

    rank: th.Tensor  # (B, M, N) pick steps of each task's best decode (−1: not picked)
    profit: th.Tensor  # (B, M) its profit
    base: th.Tensor  # (B, M) the profit of the deterministic decode

    @classmethod
    def of_decode(cls, st: SelectState) -> SelectSearchResult:
        """The result of the deterministic decode ``st`` alone: its teams, its profit as the best and as the base."""
        profit = task_profit(st)
        return cls(st.rank, profit, profit)


def select_search(
    head: PointerHead,
    view: ObsView,
    task_of: th.Tensor,
    samples: int,
    temperature: float,
    generator: th.Generator | None = None,
    fixed_picks: bool = False,
) -> SelectSearchResult:
    """Per task, the best of the deterministic decode and ``samples`` − 1 sampled decodes of its team, by the task's
    profit (:func:`task_profit`, the select stage's return: reward on cover minus the pair costs); the deterministic
    decode wins ties (implementation detail 18). Candidate sets are disjoint, so the tasks decode independently and
    their best teams together form one decision.

    :param head: the pointer actor
    :param task_of: (B, N) task each entity is a candidate of (−1: none)
    :param samples: K, decodes per task including the deterministic one (1: that one alone)
    :param temperature: T of the sampled decodes (> 1: picks further from the argmax)
    :param generator: the random stream of the sampled decodes (None: torch's global one)
    :param fixed_picks: decode by the fixed-length loop (:func:`.decode_round`), for a traced or captured search
    """
    d = head.embed_entities(view)  # the copies share their state's entity embeddings
    base = decode_round(head, view, task_of, deterministic=True, embedded=d, fixed_picks=fixed_picks)
    if samples <= 1:
        return SelectSearchResult.of_decode(base)
    p0 = task_profit(base)
    (B, N), M, S = task_of.shape, p0.shape[1], samples - 1
    rep = select_copies(view, S)
    tr = task_of.repeat_interleave(S, 0)
    st = decode_round(head, rep, tr, False, temperature=temperature, generator=generator, embedded=d, fixed_picks=fixed_picks)
    profit = th.cat([p0.unsqueeze(1), task_profit(st).view(B, S, M)], 1)  # (B, K, M), the deterministic decode first
    best = profit.argmax(1)  # (B, M), the first maximum
    ranks = th.cat([base.rank.unsqueeze(1), st.rank.view(B, S, M, N)], 1)
    rank = th.gather(ranks, 1, best.view(B, 1, M, 1).expand(B, 1, M, N)).squeeze(1)
    return SelectSearchResult(rank, th.gather(profit, 1, best.unsqueeze(1)).squeeze(1), p0)


# The exact searches stop by work, not by the clock, so that a decision or a label does not depend on the machine's speed
# or load: a node limit under which HiGHS proves nearly every step cover optimal (docs/learning.md, "A deterministic
# stop for the exact searches"), and a time limit only as a safety net for a solve that takes pathologically long.
EXACT_NODE_LIMIT = 1000
EXACT_TIME_LIMIT = 30.0
# Nodes of :func:`task_by_task_cover`'s search over shared entities before a batch row goes to one HiGHS solve: on 54 of
# the value-aware first-round covers of RBF (top 2) 32 finished within 8 nodes, and a larger limit costs the rows that still
# go to HiGHS more than it saves (docs/benchmarks.md, "The task-by-task cover search").
SHARED_NODE_LIMIT = 8


def task_by_task_cover(
    supply: np.ndarray,
    demand: np.ndarray,
    reward: np.ndarray,
    cost: np.ndarray,
    pairs: np.ndarray,
    node_limit: int = EXACT_NODE_LIMIT,
    time_limit: float = EXACT_TIME_LIMIT,
) -> np.ndarray | None:
    """(n,) the task each entity serves in the exact most profitable cover of the allowed ``pairs`` (n, m) (−1: none),
    task by task: each task's most profitable team among its allowed entities
    (:func:`~sb3_taskalloc.baselines.milp.max_profit_team`), and where two tasks' teams share an entity, best-first
    branch and bound on it: one branch forbids it to the one task, the other to the other, which between them keep
    every cover (an entity serves one task at most). A node's bound is the sum of its tasks' team profits, each team
    chosen as if the others did not exist, so the first node whose teams are disjoint is an optimal cover. Where each
    entity may serve one task only (the candidates of a pre-assignment) the root's teams are disjoint.

    :param node_limit: HiGHS node limit of a task whose own branch and bound runs long (:func:`max_profit_team`)
    :param time_limit: HiGHS time limit of such a task (seconds), a safety net
    :return: the tasks served, or None where the search reached :data:`SHARED_NODE_LIMIT` nodes first
    """
    from sb3_taskalloc.baselines.milp import max_profit_team

    solved: dict[tuple[int, frozenset[int]], tuple[float, np.ndarray]] = {}

    def team(j: int, forbidden: frozenset[int]) -> tuple[float, np.ndarray]:
        """task j's most profitable team (its profit, its entities) without the entities ``forbidden`` to it"""
        if (j, forbidden) not in solved:
            ents = np.flatnonzero(pairs[:, j])
            ents = ents[~np.isin(ents, list(forbidden))] if forbidden else ents
            chosen = ents[max_profit_team(supply[ents], demand[j], reward[j], cost[ents, j], time_limit, node_limit)]
            solved[j, forbidden] = (float(reward[j] - cost[chosen, j].sum()) if len(chosen) else 0.0, chosen)
        return solved[j, forbidden]

    tasks = np.flatnonzero(pairs.any(0)).tolist()
    root = {j: frozenset[int]() for j in tasks}
    # A node: minus its bound, its order of creation (ties go to the older node: the search is deterministic), and what
    # it forbids to each task (its teams are read from ``solved``).
    queue = [(-sum(team(j, f)[0] for j, f in root.items()), 0, root)]
    for created in range(1, 2 * SHARED_NODE_LIMIT, 2):
        _, _, forbids = heapq.heappop(queue)
        served = np.full(len(supply), -1, dtype=np.int64)
        for j, f in forbids.items():
            members = team(j, f)[1]
            shared = members[served[members] >= 0]
            if len(shared):  # branch on the first entity two teams share
                e, other = int(shared[0]), int(served[shared[0]])
                for order, k in enumerate((other, j)):
                    child = {**forbids, k: forbids[k] | {e}}
                    heapq.heappush(queue, (-sum(team(t, g)[0] for t, g in child.items()), created + order, child))
                break
            served[members] = j
        else:
            return served
    return None


def exact_covers(
    view: ObsView,
    allowed: th.Tensor,
    node_limit: int = EXACT_NODE_LIMIT,
    time_limit: float = EXACT_TIME_LIMIT,
    by_task: bool = True,
) -> th.Tensor:
    """(B, N) the task each entity serves in the exact most profitable cover of the ``allowed`` pairs (−1: none):
    :func:`~sb3_taskalloc.baselines.milp.max_profit_cover`, the per-step MILP's formulation, on those pairs alone.
    Each batch row is solved task by task (:func:`task_by_task_cover`: each task's exact team by branch and bound,
    then branch and bound on the entities two teams share), or by one HiGHS solve on the CPU where that search runs past
    :data:`SHARED_NODE_LIMIT` nodes. Where each entity may serve one task at most (the candidates of a pre-assignment)
    the problem separates by task and no row branches.

    :param allowed: (B, N, M) bool pairs that may be assigned
    :param node_limit: HiGHS node limit per solve (a batch row, or a task whose branch and bound ran long); the best
        cover found is used when it is reached (a deterministic stop: the cover is the same on any machine)
    :param time_limit: HiGHS time limit per solve (seconds), a safety net: where it binds, the cover depends on the
        machine's speed and load
    :param by_task: solve task by task first (False: one HiGHS solve per batch row always, the reference the benchmark
        ``python -m sb3_taskalloc.bench labels`` times it against)
    """
    from sb3_taskalloc.baselines.milp import max_profit_cover

    tensors = (view.supply, view.demand, view.reward, view.pair_cost)
    supply, demand, reward, cost = (x.detach().double().cpu().numpy() for x in tensors)
    pairs = allowed.cpu().numpy()
    members = np.full(pairs.shape[:2], -1, dtype=np.int64)
    for b in range(pairs.shape[0]):
        ents, tasks = np.flatnonzero(pairs[b].any(1)), np.flatnonzero(pairs[b].any(0))
        if len(ents) == 0:
            continue
        if by_task:
            found = task_by_task_cover(supply[b], demand[b], reward[b], cost[b], pairs[b], node_limit, time_limit)
            if found is not None:
                members[b] = found
                continue
        x, _, _ = max_profit_cover(
            supply[b, ents],
            demand[b, tasks],
            reward[b, tasks],
            cost[b][np.ix_(ents, tasks)],
            pairs[b][np.ix_(ents, tasks)],
            time_limit=time_limit,
            node_limit=node_limit,
        )
        e, t = np.nonzero(x)
        members[b, ents[e]] = tasks[t]
    return th.as_tensor(members, device=allowed.device)


def cover_search(
    head: PointerHead,
    view: ObsView,
    task_of: th.Tensor,
    node_limit: int = EXACT_NODE_LIMIT,
    time_limit: float = EXACT_TIME_LIMIT,
    against: SelectSearchResult | None = None,
    members: th.Tensor | None = None,
) -> SelectSearchResult:
    """Per task, the better of the teams ``against`` (default: the deterministic decode) and the exact most profitable
    cover of its candidates (:func:`exact_covers` on the candidate pairs alone), by the task's profit
    (:func:`task_profit`); the teams ``against`` win ties (implementation detail 18). The cover's team is decoded by the
    pointer among its members alone, so its pick order is the pointer's own and a distillation of it teaches which
    entities to pick, not an order.

    :param head: the pointer actor
    :param task_of: (B, N) task each entity is a candidate of (−1: none)
    :param node_limit: HiGHS node limit per batch row (:func:`exact_covers`)
    :param time_limit: HiGHS time limit per batch row (seconds), a safety net (:func:`exact_covers`)
    :param against: an earlier search's teams on the same candidates (:func:`select_search`), so the deterministic
        decode is not decoded twice
    :param members: (B, N) the exact cover of the candidate pairs where the caller has it already (None: solved here)
    """
    if against is None:
        against = SelectSearchResult.of_decode(decode_round(head, view, task_of, deterministic=True))
    if members is None:
        allowed = task_of.unsqueeze(-1) == th.arange(view.task_mask.shape[1], device=task_of.device)
        members = exact_covers(view, allowed, node_limit, time_limit)
    cover = decode_round(head, view, members, deterministic=True)
    p1 = task_profit(cover)
    better = p1 > against.profit
    return SelectSearchResult(
        th.where(better.unsqueeze(-1), cover.rank, against.rank), th.where(better, p1, against.profit), against.base
    )


class SearchResult(NamedTuple):
    candidates: th.Tensor  # (B, N) the best pre-assignment found (task per free entity, −1 otherwise)
    profit: th.Tensor  # (B,) its step profit
    base: th.Tensor  # (B,) the step profit of the argmax pre-assignment


def sampled_search(
    dist: MaskedCategorical,
    head: PointerHead,
    view: ObsView,
    samples: int,
    temperature: float,
    generator: th.Generator | None = None,
) -> SearchResult:
    """The best of the argmax pre-assignment and ``samples`` − 1 joint pre-assignments drawn from π^(1/T), by the step's
    profit (:func:`round_profit`), all decoded in one batched pass; the argmax wins ties (implementation detail 16).

    :param dist: the pre-assign actor's distribution on ``view``
    :param head: the pointer actor, decoding deterministically
    :param samples: K, pre-assignments per state including the argmax (1: the argmax alone)
    :param temperature: T of the samples (> 1: more entities leave their argmax)
    :param generator: the random stream of the samples (None: torch's global one)
    """
    B, N = view.assignable.shape
    free = view.assignable
    c = th.where(free, dist.get_actions(True), -1)  # (B, N)
    if samples <= 1:
        base = round_profit(head, view, c)
        return SearchResult(c, base, base)
    probs = th.softmax(dist.logits / temperature, -1).reshape(B * N, -1)
    drawn = th.multinomial(probs, samples - 1, replacement=True, generator=generator).view(B, N, samples - 1)
    cs = th.cat([c.unsqueeze(1), th.where(free.unsqueeze(1), drawn.transpose(1, 2), -1)], 1)  # (B, K, N), the argmax first
    rep = ObsView(*(x.repeat_interleave(samples, 0) for x in view))
    profit = round_profit(head, rep, cs.reshape(B * samples, N)).view(B, samples)
    best = profit.argmax(1)  # the first maximum: the argmax itself where nothing beats it
    rows = th.arange(B, device=c.device)
    return SearchResult(cs[rows, best], profit[rows, best], profit[:, 0])
