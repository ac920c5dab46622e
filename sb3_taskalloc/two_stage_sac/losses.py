"""Losses of TwoStageSAC, one function per term (implementation details 2–5 and 12 of
:mod:`sb3_taskalloc.two_stage_sac`).

Every function takes the networks and tensors it needs and returns tensors: none reads the algorithm's state. Both
prior terms come the same way: the frozen initial actor (``prior``) and its weight (``prior_coef``), the term being
skipped when the weight is 0 or there is no prior.
"""

from __future__ import annotations

from typing import NamedTuple

import torch as th
from torch.nn import functional as F

from sb3_taskalloc.common.distributions import MaskedCategorical, SegmentedCategorical, segment_sum
from sb3_taskalloc.common.policies import CriticContext, PreAssignActor, SelectCritic, Selector, TwinCritic
from sb3_taskalloc.common.torch_layers import ObsView, PointerHead
from sb3_taskalloc.two_stage_sac.search import select_search
from sb3_taskalloc.two_stage_sac.select_stage import TeacherForcedRound, own_column, stored_rounds, teacher_forced


def constant_mix(critic: TwinCritic, contexts: list[CriticContext], assign: th.Tensor) -> tuple[th.Tensor, ...]:
    """``critic.mix(contexts, assign)`` with the critic's parameters as constants: autograd records only the path through
    ``assign`` (and the contexts, which the actor loss detaches), and no gradient reaches the critic. Unlike switching
    ``requires_grad`` off and on around the call, this traces whole (``torch.compile``)."""
    params = {name: p.detach() for name, p in critic.named_parameters()}
    return th.func.functional_call(critic, params, (None, assign), {"contexts": contexts})  # type: ignore[no-any-return]


def mask_weights(mask: th.Tensor) -> th.Tensor:
    """The weights of a mean over the entries of ``mask`` that a fixed-shape loss sums in place of selecting them:
    1 / #entries where ``mask`` holds, else 0 (all 0 when it holds nowhere)."""
    return mask.float() / mask.sum().clamp_min(1)


# ---------------------------------------------------------------------------------------------- stage 1: pre-assign


def state_entropy(dist: MaskedCategorical, view: ObsView, per_entity: bool = False) -> th.Tensor:
    """(B,) the entropy bonus of a state: H(s) = Σ_i H(π_i(·|s)) over free entities (the joint entropy of the factorised
    policy, the paper's), or with ``per_entity`` its mean over the free entities, which does not grow with their number.
    """
    total = dist.entropy().sum(1)
    if not per_entity:
        return total
    return total / view.assignable.sum(1).clamp_min(1)


class EntropyTerms(NamedTuple):
    entropy: th.Tensor  # mean per-entity entropy H̄(s) of each state with a free entity; weighted: of every state
    target: th.Tensor  # its target H̄* = ratio × mean_i log(#valid tasks)
    weight: th.Tensor | None = None  # weighted: each state's weight in the mean, 1 / #states with a free entity, else 0


def preassign_entropy(
    dist: MaskedCategorical, view: ObsView, target_entropy_ratio: float, weighted: bool = False
) -> EntropyTerms:
    """Statistics of the temperature loss (implementation detail 4) over the states that have a free entity, selected,
    or with ``weighted`` kept in place with a weight of 0 where there is none: a fixed shape and no host read, which
    traces as one graph (``torch.compile``)."""
    n_free = view.assignable.sum(1)
    has_free = n_free > 0
    mean_entropy = dist.entropy().sum(1) / n_free.clamp_min(1)
    target = target_entropy_ratio * th.log(view.task_mask.sum(1).float().clamp_min(1))
    if weighted:
        return EntropyTerms(mean_entropy, target, mask_weights(has_free))
    return EntropyTerms(mean_entropy[has_free], target[has_free])


def preassign_actor_loss(
    dist: MaskedCategorical,
    critic: TwinCritic,
    contexts: list[CriticContext],
    view: ObsView,
    alpha: th.Tensor,
    prior: PreAssignActor | None = None,
    prior_coef: float = 0.0,
    entropy_per_entity: bool = False,
) -> th.Tensor:
    """The paper's L_actor(θ) with the true entropy and the expectation over actions (implementation detail 3): mean over
    the batch of −α·H(s) − min_k AMIX^k(Σ_j π_i(j|s) Q^k_i(s, j)), plus β Σ_i KL(π_i ‖ π₀_i) with a prior
    (implementation detail 12).

    The critics are frozen and their contexts detached, so autograd records only the path through π: no backward pass
    through the critic networks.

    :param dist: the actor's distribution on ``view``
    :param contexts: the critics' contexts on ``view`` (:meth:`~TwinCritic.contexts`)
    :param prior: the frozen initial actor π₀; :param prior_coef: β
    :param entropy_per_entity: the bonus is the mean per-entity entropy, as in the critic's target
    """
    q_pi = th.stack(constant_mix(critic, [ctx.detach() for ctx in contexts], dist.probs), dim=0).min(0).values
    loss = -alpha * state_entropy(dist, view, entropy_per_entity) - q_pi
    if prior_coef > 0 and prior is not None:
        with th.no_grad():
            prior_dist = prior(view)
        loss = loss + prior_coef * dist.kl(prior_dist).sum(1)
    return loss.mean()


def ent_coef_loss(log_alpha: th.Tensor, entropy: th.Tensor, target: th.Tensor, weight: th.Tensor | None = None) -> th.Tensor:
    """log α·(H − H*): α grows while the entropy is below its target (SB3's SAC, per-entity or per-pick entropies).

    :param weight: each entropy's weight in the mean (summing to 1; None: equal weights)
    """
    if weight is not None:
        return (log_alpha * ((entropy - target).detach() * weight)).sum()
    return (log_alpha * (entropy - target).detach()).mean()


# ------------------------------------------------------------------------------------------------- stage 2: select


class SelectLosses(NamedTuple):
    n: int | th.Tensor  # transitions (a tensor where the steps are padded: counting them would wait for the device)
    critic_loss: th.Tensor
    actor_loss: th.Tensor
    target: th.Tensor  # (n,) TD targets; padded: (T, B, M), 0 where no pick happened
    entropy: th.Tensor  # (n,) entropy of each pick's distribution; padded: (T, B, M)
    target_entropy: th.Tensor  # (n,) ratio × log(#choices); padded: (T, B, M)
    weight: th.Tensor | None = None  # padded: (T, B, M) each transition's weight in the means, 1 / n where a pick happened


def select_losses(
    selector: Selector,
    critic: SelectCritic,
    critic_target: SelectCritic,
    view: ObsView,
    candidates: th.Tensor,
    pick_rank: th.Tensor,
    preassign: bool,
    alpha: th.Tensor,
    target_entropy_ratio: float,
    prior: Selector | None = None,
    prior_coef: float = 0.0,
    steps: int | None = None,
) -> SelectLosses | None:
    """Discrete-SAC losses of the select stage on the stored pick orders (implementation detail 5):
    Q^k(s_t, a_t) → r_t + (1 − done_t)·Σ_a π(a|s_{t+1})[min_k Q̄^k(s_{t+1}, a) − α_s log π(a|s_{t+1})] (γ = 1 within a
    task) and the actor loss Σ_a π(a|s_t)[α_s log π(a|s_t) − min_k Q^k(s_t, a)] (+ β_s KL(π ‖ π₀) with a prior).

    All steps of all tasks of all rows are evaluated in one batched pass (:func:`teacher_forced`).

    :param candidates: (B, M, N) stored candidate sets; :param pick_rank: (B, M, N) stored pick steps
    :param preassign: the decisions came from pre-assignment (one round) or a shared pool (one round per task)
    :param steps: pad every round to this many pick steps (N always suffices) and weigh the transitions instead of
        selecting them: the same losses up to rounding, from tensors of fixed shape with no host read, so that the
        losses trace as one graph (``torch.compile(fullgraph=True)``); None: as many steps as the batch's longest team
    :return: the losses, or None when ``steps`` is None and the batch holds no pick
    """
    rounds = stored_rounds(candidates, preassign)
    if len(rounds) > 1:  # W/o Pre: the rounds are independent given their candidate sets, so stack them as rows
        n = len(rounds)
        view = ObsView(*(x.repeat(n, *([1] * (x.dim() - 1))) for x in view))
        pick_rank = pick_rank.repeat(n, 1, 1)
    head = selector.head
    tf = teacher_forced(view, th.cat(rounds, 0), pick_rank, steps)
    if tf is None:
        return None
    M = pick_rank.shape[1]
    logits = head(head.embed_entities(view), tf.task_state, tf.dyn, tf.task_of)
    dist = SegmentedCategorical(logits, tf.choices, tf.seg, M)
    qs = critic(critic.embed(view), tf.task_state, tf.dyn, tf.task_of)  # (T, B, N) each
    with th.no_grad():
        q_targ = th.stack(critic_target(critic_target.embed(view), tf.task_state, tf.dyn, tf.task_of), 0).min(0).values
        v = dist.expect(q_targ - alpha * dist.log_probs)  # V(s_t), (T, B, M)
        v_next = th.cat([v[1:], th.zeros_like(v[:1])], 0)
    min_q = th.stack(qs, 0).min(0).values.detach()
    actor = dist.expect(alpha * dist.log_probs - min_q)
    if prior_coef > 0 and prior is not None:
        with th.no_grad():
            p_head = prior.head
            p_logits = p_head(p_head.embed_entities(view), tf.task_state, tf.dyn, tf.task_of)
            prior_dist = SegmentedCategorical(p_logits, tf.choices, tf.seg, M)
        actor = actor + prior_coef * dist.kl(prior_dist)
    valid = tf.valid
    q_sa = th.stack([segment_sum(tf.picked * q, tf.seg, M) for q in qs], dim=-1)  # (T, B, M, n_critics)
    target = (tf.reward + (1 - tf.done.float()) * v_next).detach()
    n_choices = segment_sum(tf.choices.float(), tf.seg, M)
    target_entropy = target_entropy_ratio * th.log(n_choices.clamp_min(1))
    if steps is not None:  # the same means, each transition weighted (1 / n where a pick happened, else 0)
        weight = mask_weights(valid)
        critic_loss = 0.5 * sum((((q_sa[..., k] - target) ** 2) * weight).sum() for k in range(q_sa.shape[-1]))
        return SelectLosses(
            valid.sum(),
            critic_loss,  # type: ignore[arg-type]
            (actor * weight).sum(),
            target * valid,
            dist.entropy(),
            target_entropy,
            weight,  # type: ignore[arg-type]
        )
    q_sa, target = q_sa[valid], target[valid]  # (n, n_critics), (n,)
    critic_loss = 0.5 * sum(F.mse_loss(q_sa[:, k], target) for k in range(q_sa.shape[-1]))
    return SelectLosses(
        n=int(target.numel()),
        critic_loss=critic_loss,  # type: ignore[arg-type]
        actor_loss=actor[valid].mean(),
        target=target,
        entropy=dist.entropy()[valid],
        target_entropy=target_entropy[valid],
    )


class SelectSearchLoss(NamedTuple):
    loss: th.Tensor  # −mean over the improved tasks of log π(a*) = Σ_t log π(a*_t | s*_t) (0 if none improved)
    improved: th.Tensor  # share of the tasks with candidates where a sampled team beat the deterministic one
    gain: th.Tensor  # mean profit gain of the best team over the deterministic one, over those tasks


def select_search_loss(
    selector: Selector, view: ObsView, candidates: th.Tensor, samples: int, temperature: float, steps: int | None = None
) -> SelectSearchLoss:
    """Distillation of a select-stage search (implementation detail 18): per task of the stored first round, the best
    of its deterministic team and ``samples`` − 1 sampled teams by the task's profit (:func:`.select_search`); where it
    beats the deterministic team the loss raises the log-probability of its pick sequence, teacher-forced.

    :param candidates: (B, M, N) stored candidate sets of pre-assigned decisions
    :param samples: K, decodes per task including the deterministic one (1: the term is 0)
    :param temperature: T of the sampled decodes
    :param steps: decode and teacher-force with a fixed number of pick steps (N) and weigh the tasks instead of
        selecting them, as :func:`select_losses` does with it: one graph when traced; None: the stopping decode
    """
    (task_of,) = stored_rounds(candidates, preassign=True)
    head = selector.head
    with th.no_grad():
        found = select_search(head, view, task_of, samples, temperature, fixed_picks=steps is not None)
        improved = found.profit > found.base
        has = candidates.any(-1) & view.task_mask
    if steps is not None:  # the same means over weighted tasks, with no host read
        log_p = team_log_prob(head, view, task_of, found.rank, steps)
        assert log_p is not None  # a fixed number of steps is always laid out
        over_has = mask_weights(has)
        gain, share = ((found.profit - found.base) * over_has).sum(), (improved * over_has).sum()
        return SelectSearchLoss(-(log_p * mask_weights(improved)).sum(), share, gain)
    with th.no_grad():
        gain = (found.profit - found.base)[has].mean() if bool(has.any()) else found.profit.new_zeros(())
        share = improved[has].float().mean() if bool(has.any()) else found.profit.new_zeros(())
    log_p = team_log_prob(head, view, task_of, found.rank) if bool(improved.any()) else None
    if log_p is None:
        return SelectSearchLoss(found.profit.new_zeros(()), share, gain)
    return SelectSearchLoss(-log_p[improved].mean(), share, gain)


def pick_log_probs(
    head: PointerHead, view: ObsView, task_of: th.Tensor, pick_rank: th.Tensor, steps: int | None = None
) -> tuple[TeacherForcedRound, th.Tensor] | None:
    """The teacher-forced states of a stored decoding round (:func:`.teacher_forced`) and the pointer's
    log-probabilities (T, B, N) of every choice at each of them, or None when no task picks anything.

    :param task_of: (B, N) task each entity is a candidate of (−1: none)
    :param pick_rank: (B, M, N) step at which task j picks entity i (−1: not picked); every pick must be a valid choice
        of its step, as a decode's are
    :param steps: the steps to lay out (:func:`.teacher_forced`)
    """
    tf = teacher_forced(view, task_of, pick_rank, steps)
    if tf is None:
        return None
    logits = head(head.embed_entities(view), tf.task_state, tf.dyn, tf.task_of)
    return tf, SegmentedCategorical(logits, tf.choices, tf.seg, pick_rank.shape[1]).log_probs


def team_log_prob(
    head: PointerHead, view: ObsView, task_of: th.Tensor, pick_rank: th.Tensor, steps: int | None = None
) -> th.Tensor | None:
    """(B, M) Σ_t log π(a_t|s_t) of each task's stored pick sequence under the pointer, teacher-forced
    (:func:`pick_log_probs`, ``steps`` as there; 0 for a task that picks nothing), or None when no task picks anything."""
    found = pick_log_probs(head, view, task_of, pick_rank, steps)
    if found is None:
        return None
    tf, log_probs = found
    return segment_sum(tf.picked * log_probs, tf.seg, pick_rank.shape[1]).sum(0)


def cover_imitation_loss(
    head: PointerHead,
    view: ObsView,
    task_of: th.Tensor,
    pick_rank: th.Tensor,
    labelled: th.Tensor,
    as_set: bool = False,
) -> th.Tensor:
    """The supervised loss of :meth:`.TwoStageSAC.distill_select` (implementation detail 19), −mean over the labelled
    tasks of Σ_t log p_t along their labelled teams (teacher-forced), where p_t is

    - the probability of the labelled pick a*_t (``as_set=False``; the sum is the team's :func:`team_log_prob`);
    - the probability of picking any member of the team not picked yet, Σ_{i ∈ A*, rank(i) ≥ t} π_t(i) (``as_set=True``):
      a cover is a set, and any of its remaining members is a right pick at step t, so the order the label happens to
      list them in is not taught.

    :param labelled: (B, M) tasks whose team in ``pick_rank`` is a label
    """
    if not bool(labelled.any()):
        return view.reward.new_zeros(())
    if not as_set:
        log_p = team_log_prob(head, view, task_of, pick_rank)
        return view.reward.new_zeros(()) if log_p is None else -log_p[labelled].mean()
    found = pick_log_probs(head, view, task_of, pick_rank)
    if found is None:
        return view.reward.new_zeros(())
    tf, log_probs = found
    M = pick_rank.shape[1]
    probs = log_probs.exp()  # (T, B, N)
    rank_own = th.where(task_of >= 0, own_column(pick_rank.transpose(1, 2), task_of), -1)  # (B, N)
    steps = th.arange(probs.shape[0], device=probs.device).view(-1, 1, 1)
    remaining = (rank_own >= steps) & tf.choices  # (T, B, N) members not picked before t
    p_set = segment_sum(probs * remaining.float(), tf.seg, M)  # (T, B, M)
    log_p = th.where(tf.valid, p_set.clamp_min(1e-12).log(), 0.0).sum(0)  # (B, M)
    return -log_p[labelled].mean()
