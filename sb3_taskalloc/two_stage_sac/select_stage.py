"""The select stage: a short MDP per task, in which the task picks its team among its candidates (paper Algorithm 1,
stage 2).

State: the task's remaining demand, the cost of its picks so far, how many it made and which candidates are left.
Action: pick one candidate. Transition (:func:`transition`): the demand drops by the pick's supply (clipped at 0); the
reward is −(pair cost of the pick), plus the task's reward when the pick covers the demand; the task is done when it is
covered or can no longer be kept. γ = 1 within a task.

The same transition serves the decoder (:class:`SelectState`, one pick per task per step for every task of every batch
row in parallel) and the losses (:func:`teacher_forced`, every step of stored pick orders at once).
"""

from __future__ import annotations

import copy
from typing import NamedTuple

import torch as th

from sb3_taskalloc.common.distributions import segment_pick, segment_sum
from sb3_taskalloc.common.torch_layers import ObsView, PointerHead, symlog

#: A task counts as covered (internally) when every remaining demand is at most this (the env's tolerance is larger).
COVER_TOL = 1e-5
#: :func:`decode_round` drops the rows with no active task once the rows still decoding are at most this share of those it
#: decodes: a pick step's work is per row, and dropping rows costs a copy of the state.
COMPACT_SHARE = 0.75


class Decision(NamedTuple):
    """One two-stage decision for a batch of observations."""

    env_action: th.Tensor  # (B, N) task slot per entity, M = unassigned
    candidates: th.Tensor  # (B, M, N) bool: entity i was a candidate of task j
    pick_rank: th.Tensor  # (B, M, N) long: step at which task j picked entity i, −1 if not
    kept: th.Tensor  # (B, M) bool: task covered with positive internal profit


def own_column(x: th.Tensor, task_of: th.Tensor) -> th.Tensor:
    """(B, N) ``x[b, i, task_of[b, i]]``: each entity's entry for its own task (arbitrary where task_of < 0).

    :param x: (B, N, M) per entity and task
    :param task_of: (B, N) task each entity is a candidate of (−1: none)
    """
    return th.gather(x, 2, task_of.clamp_min(0).unsqueeze(-1)).squeeze(-1)


def useful_supply(view: ObsView, task_of: th.Tensor, rem: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """What each candidate would contribute to its task now: Σ_k min(s_ik, d_jk) for j = its task.

    :param task_of: (B, N) task each entity is a candidate of (−1: none)
    :param rem: (..., B, M, K) remaining demand
    :return: the useful supply (..., B, N) and the remaining demand of each entity's task (..., B, N, K)
    """
    idx = task_of.clamp_min(0).expand(*rem.shape[:-3], -1, -1)
    rem_i = th.gather(rem, -2, idx.unsqueeze(-1).expand(*idx.shape, rem.shape[-1]))
    return th.minimum(view.supply, rem_i).sum(-1), rem_i


def choosable(
    view: ObsView,
    task_of: th.Tensor,
    avail: th.Tensor,
    rem: th.Tensor,
    useful: tuple[th.Tensor, th.Tensor] | None = None,
) -> th.Tensor:
    """(..., B, N) candidates not picked yet that would cover some of their task's remaining demand: the choices (a
    candidate that covers nothing could only add cost).

    :param avail: (..., B, N) candidates not picked yet; see :func:`useful_supply` for the others
    :param useful: :func:`useful_supply` of (``task_of``, ``rem``) when already computed
    """
    return avail & ((useful or useful_supply(view, task_of, rem))[0] > COVER_TOL)


def still_winnable(
    view: ObsView, task_of: th.Tensor, choices: th.Tensor, pc_own: th.Tensor, rem: th.Tensor, cost: th.Tensor
) -> th.Tensor:
    """Whether each uncovered task can still be kept: its choices can cover the remaining demand, and the cost so far
    plus the cheapest of them stays below the reward (covering needs at least one more pick). A task that cannot is
    abandoned at once (its decoding stops): pair costs are non-negative, so it would end uncovered or unprofitable
    anyway and the env action is the same as decoding on. Feasibility needs no per-pair minimum:
    Σ_i min(s_ik, d_k) ≥ d_k holds exactly when Σ_i s_ik ≥ d_k.

    :param task_of: (B, N) task each entity is a candidate of (−1: none)
    :param choices: (..., B, N) the choices of :func:`choosable`
    :param pc_own: (B, N) pair cost of each entity for the task it is a candidate of
    :param rem: (..., B, M, K) remaining demand; :param cost: (..., B, M) pair costs of the picks so far
    :return: (..., B, M) bool
    """
    M = rem.shape[-2]
    seg = task_of.clamp_min(0).expand_as(choices)
    cand = choices & (task_of >= 0)
    supply_left = segment_sum(cand.unsqueeze(-1) * view.supply, seg, M, vector=True)  # (..., B, M, K)
    own_cost = pc_own.expand_as(cand).masked_fill(~cand, th.inf)
    cheapest = own_cost.new_full((*cand.shape[:-1], M), th.inf).scatter_reduce_(-1, seg, own_cost, "amin")  # inf: none
    return (supply_left >= rem - COVER_TOL).all(-1) & (view.reward - cost - cheapest > 0)


def transition(
    view: ObsView,
    task_of: th.Tensor,
    valid: th.Tensor,
    pick_cost: th.Tensor,
    rem_after: th.Tensor,
    cost_after: th.Tensor,
    choices_after: th.Tensor,
    pc_own: th.Tensor,
) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
    """Reward and end of one pick of every task (for one or many (leading dims) steps).

    :param valid: (..., B, M) tasks that pick at this step
    :param pick_cost: (..., B, M) pair cost of the pick
    :param rem_after: (..., B, M, K) remaining demand after the pick
    :param cost_after: (..., B, M) pair costs of the picks so far, this one included
    :param choices_after: (..., B, N) the choices after the pick (:func:`choosable`)
    :param pc_own: (B, N) pair cost of each entity for the task it is a candidate of
    :return: reward (−pick cost, + the task reward when the pick covers the demand), done (covered, or no longer
        :func:`still_winnable`) and newly covered, each (..., B, M)
    """
    newly = valid & (rem_after <= COVER_TOL).all(-1)
    done = valid & (newly | ~still_winnable(view, task_of, choices_after, pc_own, rem_after, cost_after))
    reward = valid.float() * (-pick_cost + view.reward * newly.float())
    return reward, done, newly


def select_features(
    view: ObsView,
    task_of: th.Tensor,
    pc_own: th.Tensor,
    rem: th.Tensor,
    cost: th.Tensor,
    npick: th.Tensor,
    useful: tuple[th.Tensor, th.Tensor] | None = None,
) -> tuple[th.Tensor, th.Tensor]:
    """Inputs of the pointer heads for one or many (leading dims) select-stage states.

    :param view: observations (B, ...)
    :param task_of: (B, N) task each entity is a candidate of (−1: none)
    :param pc_own: (B, N) pair cost of each entity for that task
    :param rem: (..., B, M, K) remaining demand; :param cost: (..., B, M) cost of the picks; :param npick: (..., B, M)
    :param useful: :func:`useful_supply` of (``task_of``, ``rem``) when already computed
    :return: task states (..., B, M, K + 4) and dynamic entity features (..., B, N, SELECT_DYN): coverage of the
        remaining demand, symlog pair cost, symlog margin m (reward − cost so far − pair cost), relu(m), waste share of
        the supply, whether the entity alone covers the remaining demand, and symlog of its unit cost (pair cost per
        unit of the remaining demand it covers), a fixed basis that the pointer weighs linearly
    """
    demand_sum = view.demand.sum(-1).clamp_min(1e-6)
    reward = view.reward.expand_as(cost)
    task_state = th.cat(
        [
            symlog(rem),
            symlog(reward).unsqueeze(-1),
            symlog(cost).unsqueeze(-1),
            symlog(npick).unsqueeze(-1),
            (rem.sum(-1) / demand_sum).unsqueeze(-1),
        ],
        dim=-1,
    )
    idx = task_of.clamp_min(0).expand(*rem.shape[:-3], -1, -1)
    useful_i, rem_i = useful or useful_supply(view, task_of, rem)
    cov = useful_i / rem_i.sum(-1).clamp_min(1e-6)
    waste = 1.0 - useful_i / view.supply.sum(-1).clamp_min(1e-6)
    margin = th.gather(reward - cost, -1, idx) - pc_own
    m = symlog(margin)
    unit_cost = symlog(pc_own / useful_i.clamp_min(1e-6))  # the greedy allocator's key: cost per unit of demand covered
    covers = (cov >= 1 - 1e-6).float()
    columns = [cov, symlog(pc_own).expand_as(cov), m, th.relu(m), waste, covers, unit_cost]
    return task_state, th.stack(columns, dim=-1)


class SelectState:
    """State of the select stage for every task of every batch row, advanced one pick per task at a time.

    Each entity takes part in the decoding of at most one task (``task_of``), so all tasks of all rows decode in
    parallel: the per-task state is the remaining demand, the cost of the picks so far and the number of picks.

    :param view: the observations
    :param task_of: (B, N) task whose candidate entity i is in this round (−1: none)
    """

    def __init__(self, view: ObsView, task_of: th.Tensor) -> None:
        B, N = task_of.shape
        M = view.task_mask.shape[1]
        self.view = view
        self.task_of = task_of
        self.slots = th.arange(M, device=task_of.device)
        self.seg = task_of.unsqueeze(1) == self.slots.view(1, M, 1)  # (B, M, N) candidates of task j
        self.seg_of = task_of.clamp_min(0)  # (B, N) the segment of each entity in the pick (:func:`segment_pick`)
        self.avail = task_of >= 0  # (B, N) candidates not picked yet
        self.rem = view.demand.clone()
        self.cost = th.zeros(B, M, device=task_of.device)
        self.npick = th.zeros(B, M, device=task_of.device)
        self.covered = th.zeros(B, M, dtype=th.bool, device=task_of.device)
        self.rank = th.full((B, M, N), -1, dtype=th.long, device=task_of.device)  # step at which task j picked i
        self.pc_own = own_column(view.pair_cost, task_of)  # (B, N)
        self.useful = useful_supply(view, task_of, self.rem)  # shared by the choices and the pointer's features
        self.choosable = choosable(view, task_of, self.avail, self.rem, self.useful)  # (B, N)
        self.active = view.task_mask & still_winnable(view, task_of, self.choosable, self.pc_own, self.rem, self.cost)

    def features(self) -> tuple[th.Tensor, th.Tensor]:
        """Task states (B, M, K + 4) and entity dynamic features (B, N, SELECT_DYN) for the pointer heads."""
        return select_features(self.view, self.task_of, self.pc_own, self.rem, self.cost, self.npick, self.useful)

    def choice_mask(self) -> th.Tensor:
        """(B, M, N) entities task j may pick now."""
        return self.seg & self.choosable.unsqueeze(1) & self.active.unsqueeze(-1)

    def allowed(self) -> th.Tensor:
        """(B, N) entities their task may pick now: :meth:`choice_mask` folded over the tasks (each entity is at most
        one task's candidate)."""
        return self.choosable & (self.task_of >= 0) & th.gather(self.active, 1, self.task_of.clamp_min(0))

    def advance(self, picks: th.Tensor, valid: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Apply one pick per task. :param picks: (B, M) entity index; :param valid: (B, M) rows that pick.
        :return: the :func:`transition`'s reward and done flags, both (B, M)."""
        v = self.view
        vf = valid.float()
        pc = th.gather(v.pair_cost, 1, picks.unsqueeze(1)).squeeze(1)  # (B, M): pair_cost[b, picks[b, j], j]
        sup = th.gather(v.supply, 1, picks.unsqueeze(-1).expand(-1, -1, v.supply.shape[-1]))  # (B, M, K)
        self.rem = th.where(valid.unsqueeze(-1), (self.rem - sup).clamp_min(0.0), self.rem)
        self.cost = self.cost + vf * pc
        self.npick = self.npick + vf
        # The valid picks are distinct entities (each is one task's candidate); an invalid pick goes to a spare column.
        B, N = self.avail.shape
        picked = self.avail.new_zeros(B, N + 1).scatter_(1, th.where(valid, picks, N), True)[:, :N]
        self.avail = self.avail & ~picked
        self.useful = useful_supply(v, self.task_of, self.rem)
        self.choosable = choosable(v, self.task_of, self.avail, self.rem, self.useful)
        reward, done, newly = transition(v, self.task_of, valid, pc, self.rem, self.cost, self.choosable, self.pc_own)
        self.covered = self.covered | newly
        self.active = self.active & ~done
        return reward, done

    #: The per-row fields that a pick changes, and those it leaves as they are (:meth:`take`, :meth:`put`).
    CHANGING = ("avail", "rem", "cost", "npick", "covered", "rank", "choosable", "active")
    FIXED = ("task_of", "seg", "seg_of", "pc_own")

    def take(self, rows: th.Tensor) -> SelectState:
        """The state of the batch rows ``rows`` alone, to decode on without the others."""
        part = copy.copy(self)
        part.view = ObsView(*(x[rows] for x in self.view))
        part.useful = (self.useful[0][rows], self.useful[1][rows])
        for name in self.CHANGING + self.FIXED:
            setattr(part, name, getattr(self, name)[rows])
        return part

    def put(self, rows: th.Tensor, part: SelectState) -> None:
        """Write back ``part``, the :meth:`take` of ``rows`` advanced since, into those rows."""
        for name in self.CHANGING:
            getattr(self, name)[rows] = getattr(part, name)
        self.useful[0][rows], self.useful[1][rows] = part.useful

    def kept(self) -> th.Tensor:
        """(B, M) tasks whose internal profit (reward if covered − Σ pair costs) is positive; others are abandoned."""
        return self.covered & (self.view.reward - self.cost > 0)


def decode_round(
    head: PointerHead | None,
    view: ObsView,
    task_of: th.Tensor,
    deterministic: bool,
    uniform: bool = False,
    temperature: float = 1.0,
    generator: th.Generator | None = None,
    fixed_picks: bool = False,
    embedded: th.Tensor | None = None,
    steps: int | None = None,
) -> SelectState:
    """Decode the teams of every task of one round in parallel (one pick per task per step).

    :param head: the pointer actor (None: uniformly random valid picks, the warm-up's exploration)
    :param task_of: (B, N) task each entity is a candidate of in this round (−1: none)
    :param deterministic: argmax picks (else sampled)
    :param temperature: T of sampled picks, drawn from softmax(logits / T)
    :param generator: the random stream of sampled picks (None: torch's global one)
    :param fixed_picks: run all N pick steps (or ``steps``), a done task's picks masked out (``valid`` false), with no
        host check in between: a loop of fixed length and shapes that ``torch.compile(fullgraph=True)`` traces without
        a graph break (with ``generator=None``; a generator object breaks the graph). The teams and pick orders are the
        same as the default loop's, which stops once no task is active: on the CPU that check costs nothing and saves
        the steps
    :param embedded: the pointer's entity embeddings of ``view`` (``head.embed_entities(view)``) where the caller has
        them already: (B, N, H), or (B / S, N, H) when the rows are S consecutive copies of each row of a round (a
        search's copies), which the pointer then scores in wider products
    :param steps: with ``fixed_picks``, the pick steps run (default N): fewer leave a team that needs more unfinished,
        its task still ``active`` (a recorded decision's budget, :mod:`.graph_decide`)
    """
    full = st = SelectState(view, task_of)
    B, M, N = st.seg.shape
    rows = th.arange(B, device=task_of.device)  # the rows of `full` that `st` decodes
    d = None if head is None or uniform else embedded if embedded is not None else head.embed_entities(view)
    embeddings, copies = d, 1 if d is None else B // d.shape[0]
    if steps is not None and not fixed_picks:
        raise ValueError(f"steps={steps} bounds the fixed loop only: pass fixed_picks=True with it")
    for t in range(N if steps is None else steps):
        if not fixed_picks:
            live = st.active.any(1)
            n_live = int(live.sum())
            if n_live == 0:
                break
            if n_live <= COMPACT_SHARE * len(rows):
                if st is not full:
                    full.put(rows, st)
                keep = live.nonzero().squeeze(1)
                st, rows = st.take(keep), rows[keep]
                d = None if embeddings is None else embeddings[rows // copies]
        # One uniform per row of the whole batch, whatever the rows left, so the sample is the fixed loop's.
        u = None if deterministic else th.rand((B, N), generator=generator, device=task_of.device)
        u = u if u is None or st is full else u[rows]
        if d is None:
            logits = th.zeros(len(rows), N, device=task_of.device)
        else:
            task_state, dyn = st.features()
            logits = head(d, task_state, dyn, st.task_of)  # type: ignore[misc]
            if not deterministic and temperature != 1.0:
                logits = logits / temperature
        picks = segment_pick(logits, st.allowed(), st.seg_of, M, deterministic, uniforms=u)  # (B, M)
        valid = st.active.clone()
        old = th.gather(st.rank, 2, picks.unsqueeze(-1)).squeeze(-1)
        st.rank.scatter_(2, picks.unsqueeze(-1), th.where(valid, t, old).unsqueeze(-1))
        st.advance(picks, valid)
    if st is not full:
        full.put(rows, st)
    return full


def round_profit(head: PointerHead, view: ObsView, task_of: th.Tensor) -> th.Tensor:
    """(B,) the internal profit Σ_j kept_j·(r_j − Σ pair costs of j's team) of the deterministic select stage on the
    candidate sets ``task_of``: what the env credits when the teams commit (its commitment reward before decay)."""
    return task_profit(decode_round(head, view, task_of, deterministic=True)).sum(-1)


def task_profit(st: SelectState) -> th.Tensor:
    """(B, M) each task's internal profit after decoding: r_j − Σ pair costs of its team if kept, else 0."""
    return st.kept() * (st.view.reward - st.cost)


class TeacherForcedRound(NamedTuple):
    """Every select-stage transition of one decoding round of stored pick orders, with time as a leading dimension
    (T steps); the tensors are per entity (T, B, N) or per task (T, B, M), never (T, B, M, N)."""

    task_of: th.Tensor  # (B, N) task each entity is a candidate of (−1: none)
    seg: th.Tensor  # (B, N) task_of clamped at 0 (the segment of each entity)
    picked: th.Tensor  # (T, B, N) float: entity picked at step t by its own task
    valid: th.Tensor  # (T, B, M) task j picks at step t
    choices: th.Tensor  # (T, B, N) choices of the picking tasks before the pick
    reward: th.Tensor  # (T, B, M)
    done: th.Tensor  # (T, B, M)
    task_state: th.Tensor  # (T, B, M, K + 4) pointer inputs before the pick
    dyn: th.Tensor  # (T, B, N, SELECT_DYN)


def teacher_forced(
    view: ObsView, task_of: th.Tensor, pick_rank: th.Tensor, steps: int | None = None
) -> TeacherForcedRound | None:
    """All states and transitions of a stored decoding round at once.

    Under teacher forcing every state is known in advance (remaining demand after t picks = relu(demand − Σ supplies of
    the first t picks), cost = Σ their pair costs, available = not picked before t).

    :param task_of: (B, N) task each entity was a candidate of in this round (−1: none)
    :param pick_rank: (B, M, N) step at which task j picked entity i (−1: not picked)
    :param steps: T, the steps to lay out; None: as many as the round's longest team (read on the host). A fixed T ≥
        that (N always is) gives tensors of fixed shape, the steps after the last pick valid nowhere: what a traced or
        captured step needs
    :return: the round's transitions, or None when ``steps`` is None and no task picked anything
    """
    cand = task_of >= 0
    # (B, N): step at which the entity's own task picked it, −1 if never (or if it is no candidate)
    rank_own = th.where(cand, own_column(pick_rank.transpose(1, 2), task_of), -1)
    if steps is None:
        steps = int(rank_own.max().item()) + 1
        if steps <= 0:
            return None
    M = pick_rank.shape[1]
    pc_own = own_column(view.pair_cost, task_of)  # (B, N)
    seg = task_of.clamp_min(0)
    tt = th.arange(steps, device=rank_own.device).view(-1, 1, 1)
    pf = (rank_own == tt).float()  # (T, B, N): entity picked at step t (by its own task)
    valid = segment_sum(pf, seg, M) > 0  # (T, B, M): task j picks at step t
    sup = segment_sum(pf.unsqueeze(-1) * view.supply, seg, M, vector=True)  # (T, B, M, K) supply of the pick
    pc = segment_sum(pf * pc_own, seg, M)  # (T, B, M) pair cost of the pick
    sup_cum, pc_cum, n_cum = sup.cumsum(0), pc.cumsum(0), valid.float().cumsum(0)
    rem = (view.demand - (sup_cum - sup)).clamp_min(0.0)  # before the pick
    rem_after = (view.demand - sup_cum).clamp_min(0.0)
    avail = cand & ((rank_own < 0) | (rank_own >= tt))  # (T, B, N) before the pick
    avail_after = cand & ((rank_own < 0) | (rank_own > tt))
    useful = useful_supply(view, task_of, rem)  # shared by the choices and the pointer's features
    choices = choosable(view, task_of, avail, rem, useful)
    choices_after = choosable(view, task_of, avail_after, rem_after)
    mask = choices & th.gather(valid, -1, seg.expand(steps, -1, -1))  # (T, B, N) choices of the picking tasks
    reward, done, _ = transition(view, task_of, valid, pc, rem_after, pc_cum, choices_after, pc_own)
    task_state, dyn = select_features(view, task_of, pc_own, rem, pc_cum - pc, n_cum - valid.float(), useful)
    return TeacherForcedRound(task_of, seg, pf, valid, mask, reward, done, task_state, dyn)


def stored_rounds(candidates: th.Tensor, preassign: bool) -> list[th.Tensor]:
    """``task_of`` of each decoding round of stored decisions: one round (c from the candidate sets) with
    pre-assignment; one per task without it (the candidate sets then overlap).

    :param candidates: (B, M, N) bool candidate sets
    """
    if preassign:
        return [th.where(candidates.any(1), candidates.float().argmax(1), -1)]
    return [th.where(candidates[:, j], j, -1) for j in range(candidates.shape[1])]


def env_action_of(rank: th.Tensor, kept: th.Tensor) -> th.Tensor:
    """(B, N) env action from the pick ranks and kept tasks: an entity goes to the kept task that picked it, else
    "unassigned" (M)."""
    M = rank.shape[1]
    assigned = (rank >= 0) & kept.unsqueeze(-1)  # (B, M, N)
    task = assigned.float().argmax(1)
    return th.where(assigned.any(1), task, th.full_like(task, M))
