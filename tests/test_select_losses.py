"""The pointer's losses and decoding against closed forms on hand-built batches: the sequential decode, its
segmented distributions on many tasks, the team value and each round's exact profit."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from torch.nn import functional as F

from sb3_taskalloc import TwoStageSAC
from sb3_taskalloc.baselines import GreedyAllocator
from sb3_taskalloc.common.distributions import MaskedCategorical, SegmentedCategorical, masked_pick, segment_pick
from sb3_taskalloc.common.torch_layers import NEG, ObsView, parse_obs
from sb3_taskalloc.two_stage_sac import losses
from sb3_taskalloc.two_stage_sac.select_stage import SelectState, round_profit


def select_losses(policy, view, cand, rank, alpha, ratio, prior_coef: float = 0.0) -> losses.SelectLosses:
    out = losses.select_losses(
        policy.selector, policy.select_critic, policy.select_critic_target, view, cand, rank, policy.preassign, alpha,
        ratio, policy.selector_prior, prior_coef,
    )  # fmt: skip
    assert out is not None
    return out


def hand_view(reward: float = 10.0) -> ObsView:
    """One row, one task needing 2 units; entities supply 1, 1, 2 at pair costs 1, 1, 3."""
    supply = th.tensor([[[1.0], [1.0], [2.0]]])
    demand = th.tensor([[[2.0]]])
    pc = th.tensor([[[1.0], [1.0], [3.0]]])
    obs = {
        "entity_features": th.cat([pc, supply, th.zeros(1, 3, 4)], -1),
        "task_features": th.tensor([[[reward, 2.0, 0, 0, 0]]]),
        "entity_supply": supply, "task_demand": demand, "task_reward": th.tensor([[reward]]), "pair_cost": pc,
        "entity_mask": th.ones(1, 3, dtype=th.int8), "task_mask": th.ones(1, 1, dtype=th.int8),
    }  # fmt: skip
    return parse_obs(obs)


def test_select_losses_match_sequential_closed_form():
    env = gym.make("TaskAlloc/Almighty-v0", n_skills=1, specialists=2)  # K = 1, N = 3, M = 2 (only its spaces)
    m = TwoStageSAC("TAMPolicy", env, seed=0, policy_kwargs={"hidden_dim": 16}, learning_starts=0, device="cpu")
    policy = m.policy
    view = hand_view()
    cand = th.tensor([[[True, True, True]]])
    rank = th.tensor([[[0, 1, -1]]])  # picks entity 0, then entity 1: covered at step 1
    alpha = th.tensor(0.2)
    out = select_losses(policy, view, cand, rank, alpha, 0.5)
    assert out.n == 2
    # Sequential re-derivation with the inference-time state machine.
    task_of = th.zeros(1, 3, dtype=th.long)
    st = SelectState(view, task_of)
    d = policy.selector.head.embed_entities(view)
    dc, dt = policy.select_critic.embed(view), policy.select_critic_target.embed(view)
    rewards, q_sa, values, actor_terms = [], [], [], []
    for t, pick in enumerate([0, 1]):
        ts, dyn = st.features()
        mask = st.choice_mask()
        dist = MaskedCategorical(policy.selector.head(d, ts, dyn, task_of).unsqueeze(1), mask)
        qs = policy.select_critic(dc, ts, dyn, task_of)
        qt = th.minimum(*policy.select_critic_target(dt, ts, dyn, task_of))
        values.append((dist.probs[0, 0] * (qt[0] - alpha * dist.log_probs[0, 0])).sum())
        actor_terms.append((dist.probs[0, 0] * (alpha * dist.log_probs[0, 0] - th.minimum(*qs)[0])).sum())
        q_sa.append([q[0, pick] for q in qs])
        r, done = st.advance(th.tensor([[pick]]), th.tensor([[True]]))
        rewards.append(r[0, 0])
        assert bool(done[0, 0]) == (t == 1)
    assert rewards[0].item() == -1.0 and rewards[1].item() == pytest.approx(9.0)  # −cost; −cost + reward on covering
    y = th.stack([rewards[0] + values[1], rewards[1]])  # γ = 1, done after the covering pick
    th.testing.assert_close(out.target, y.detach(), atol=1e-5, rtol=1e-5)
    expected = sum(0.5 * F.mse_loss(th.stack([q_sa[0][k], q_sa[1][k]]), y.detach()) for k in range(2))
    th.testing.assert_close(out.critic_loss, expected, atol=1e-5, rtol=1e-5)
    th.testing.assert_close(out.actor_loss, th.stack(actor_terms).mean(), atol=1e-5, rtol=1e-5)
    th.testing.assert_close(out.target_entropy, 0.5 * th.log(th.tensor([3.0, 2.0])))
    # Prior term: + β KL(π ‖ π₀) per transition, π₀ from the frozen initial pointer (here moved away from it first).
    with th.no_grad():
        for param in policy.selector.parameters():
            param.add_(th.randn_like(param))
    out_prior = select_losses(policy, view, cand, rank, alpha, 0.5, prior_coef=2.0)
    out_plain = select_losses(policy, view, cand, rank, alpha, 0.5)
    st = SelectState(view, task_of)
    d, d0 = policy.selector.head.embed_entities(view), policy.selector_prior.head.embed_entities(view)
    kls = []
    for pick in [0, 1]:
        ts, dyn = st.features()
        mask = st.choice_mask()
        dist = MaskedCategorical(policy.selector.head(d, ts, dyn, task_of).unsqueeze(1), mask)
        dist0 = MaskedCategorical(policy.selector_prior.head(d0, ts, dyn, task_of).unsqueeze(1), mask)
        p, q = dist.probs[0, 0], dist0.probs[0, 0]
        kls.append((p * (th.log(p.clamp_min(1e-30)) - th.log(q.clamp_min(1e-30)))).sum())
        st.advance(th.tensor([[pick]]), th.tensor([[True]]))
    assert max(kl.item() for kl in kls) > 1e-3
    th.testing.assert_close(out_prior.actor_loss, out_plain.actor_loss + 2.0 * th.stack(kls).mean(), atol=1e-5, rtol=1e-5)
    th.testing.assert_close(out_prior.critic_loss, out_plain.critic_loss)


def test_abandoned_when_unprofitable():
    view = hand_view(reward=2.5)  # entity 2 covers alone at cost 3 > 2.5; entity 0 (cost 1) keeps the task open
    st = SelectState(view, th.tensor([[0, -1, 0]]))
    assert st.active.all()
    _, done = st.advance(th.tensor([[2]]), th.tensor([[True]]))
    assert done.all() and st.covered.all() and not st.kept().any()
    # Whatever the policy picks, the task is not kept: covering costs at least 1 + 3 or 3 > 2.5.
    env = gym.make("TaskAlloc/Almighty-v0", n_skills=1, specialists=2)
    m = TwoStageSAC("TAMPolicy", env, seed=0, policy_kwargs={"hidden_dim": 16}, device="cpu")
    for deterministic in (True, False):
        st = m.policy.select_round(view, th.tensor([[0, -1, 0]]), deterministic=deterministic)
        assert not st.kept().any() and not st.active.any()


@pytest.mark.parametrize(
    ("reward", "demand", "expect_start"),
    [(10.0, 2.0, True), (0.5, 2.0, False), (10.0, 5.0, False)],  # cheapest candidate costs 1; supplies add up to 4
)
def test_decoding_starts_only_when_task_can_be_kept(reward, demand, expect_start):
    view = hand_view(reward=reward)
    view = view._replace(demand=th.full_like(view.demand, demand))
    st = SelectState(view, th.zeros(1, 3, dtype=th.long))
    assert bool(st.active[0, 0]) == expect_start


def test_decoding_stops_once_task_cannot_be_kept():
    view = hand_view(reward=1.5)  # after one pick of cost 1, covering needs another pick of cost ≥ 1: 1 + 1 ≥ 1.5
    st = SelectState(view, th.zeros(1, 3, dtype=th.long))
    assert st.active.all()
    _, done = st.advance(th.tensor([[0]]), th.tensor([[True]]))
    assert done.all() and not st.covered.any() and not st.active.any()
    view = hand_view(reward=10.0)._replace(demand=th.tensor([[[4.0]]]))  # needs every entity
    st = SelectState(view, th.zeros(1, 3, dtype=th.long))
    _, done = st.advance(th.tensor([[0]]), th.tensor([[True]]))
    assert not done.any()  # 1 + 2 still cover the remaining 3
    _, done = st.advance(th.tensor([[1]]), th.tensor([[True]]))
    assert not done.any()
    _, done = st.advance(th.tensor([[2]]), th.tensor([[True]]))
    assert done.all() and st.covered.all() and st.kept().all()


def test_useless_candidates_are_never_choices():
    # Two resources: entities 0 and 1 bring only the first, entity 2 only the second; the task needs one of each.
    view = hand_view()._replace(supply=th.tensor([[[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]]]), demand=th.tensor([[[1.0, 1.0]]]))
    st = SelectState(view, th.zeros(1, 3, dtype=th.long))
    assert st.choice_mask()[0, 0].tolist() == [True, True, True]
    st.advance(th.tensor([[0]]), th.tensor([[True]]))
    assert st.choice_mask()[0, 0].tolist() == [False, False, True]  # entity 1 would add cost and cover nothing


def test_segmented_categorical_equals_masked_categorical_over_tasks():
    th.manual_seed(0)
    T, B, N, M = 3, 4, 9, 3
    seg = th.randint(0, M, (B, N))
    logits = th.randn(T, B, N, requires_grad=True)
    mask = th.rand(T, B, N) > 0.4
    mask[0, 0] = False  # a row with no choice at all
    seg_dist = SegmentedCategorical(logits, mask, seg, M)
    own = seg.unsqueeze(1) == th.arange(M).view(1, M, 1)  # (B, M, N)
    full = MaskedCategorical(logits.unsqueeze(2).expand(T, B, M, N), mask.unsqueeze(2) & own)
    values = th.randn(T, B, N)
    th.testing.assert_close(seg_dist.expect(values), (full.probs * values.unsqueeze(2)).sum(-1))
    th.testing.assert_close(seg_dist.entropy(), full.entropy())
    th.testing.assert_close(seg_dist.probs, (full.probs * own).sum(2))
    assert th.isfinite(seg_dist.log_probs).all() and seg_dist.entropy()[0, 0].abs().sum() == 0
    g_seg = th.autograd.grad(seg_dist.entropy().sum(), logits)[0]
    g_full = th.autograd.grad(full.entropy().sum(), logits)[0]
    th.testing.assert_close(g_seg, g_full)
    # KL to another distribution on the same choices: Σ p (log p − log q), equal in both layouts, 0 against itself.
    other = th.randn(T, B, N)
    seg_q = SegmentedCategorical(other, mask, seg, M)
    full_q = MaskedCategorical(other.unsqueeze(2).expand(T, B, M, N), mask.unsqueeze(2) & own)
    th.testing.assert_close(seg_dist.kl(seg_q), full.kl(full_q))
    p, q = full.probs, full_q.probs
    closed = (p * (th.log(p.clamp_min(1e-30)) - th.log(q.clamp_min(1e-30)))).sum(-1)
    th.testing.assert_close(full.kl(full_q), closed, atol=1e-5, rtol=1e-5)
    assert (full.kl(full_q) >= -1e-6).all() and full.kl(full_q).max() > 0.01
    th.testing.assert_close(seg_dist.kl(seg_dist), th.zeros_like(seg_dist.entropy()))


def test_segment_pick_equals_masked_pick_over_tasks():
    """The pointer's picks on (B, N) equal :func:`masked_pick` on the (B, M, N) layout it replaces, bit for bit: the argmax
    with its first-index tie rule, and a sample is that argmax of the scores perturbed by one Gumbel draw per entity
    from the seeded stream; a segment without an allowed entity gets entity 0; the samples follow each segment's
    softmax."""
    th.manual_seed(0)
    B, N, M = 6, 11, 4
    seg = th.randint(0, M, (B, N))
    allowed = th.rand(B, N) > 0.3
    allowed[0] = False  # a row with no choice at all
    scores = th.randint(-2, 3, (B, N)).float()  # ties within segments
    full = (seg.unsqueeze(1) == th.arange(M).view(1, M, 1)) & allowed.unsqueeze(1)  # (B, M, N)
    has = full.any(-1)
    assert (~has).any() and has.any()
    ties = 0
    for deterministic in (True, False):
        for seed in range(20):
            got = segment_pick(scores, allowed, seg, M, deterministic, th.Generator().manual_seed(seed))
            noisy = scores
            if not deterministic:
                u = th.rand((B, N), generator=th.Generator().manual_seed(seed)).clamp_(1e-10, 1.0 - 1e-7)
                noisy = scores - th.log(-th.log(u))
            want = masked_pick(noisy.unsqueeze(1).masked_fill(~full, NEG), True)
            assert th.equal(got[has], want[has]) and (got[~has] == 0).all()
            assert full.gather(-1, got.unsqueeze(-1)).squeeze(-1)[has].all()  # a pick is its segment's allowed entity
        top = scores.unsqueeze(1).masked_fill(~full, NEG).max(-1, keepdim=True).values
        ties += int((((scores.unsqueeze(1) == top) & full).sum(-1) > 1).sum())
    assert ties > 0  # the tie rule was exercised
    # the samples follow the softmax of each segment
    counts = th.zeros(N)
    g = th.Generator().manual_seed(1)
    row, j = 1, int(seg[1, allowed[1]][0])
    for _ in range(4000):
        counts[segment_pick(scores, allowed, seg, M, False, g)[row, j]] += 1
    members = full[row, j]
    th.testing.assert_close(counts[members] / 4000, th.softmax(scores[row, members], 0), atol=0.03, rtol=0)


def test_select_losses_match_sequential_decoding_on_many_tasks():
    """The batched, teacher-forced select-stage terms equal a step-by-step replay of the stored decisions with the
    inference-time state machine, on RBF observations where many tasks decode at once."""
    env = gym.make("TaskAlloc/RBF-v0")
    m = TwoStageSAC("TAMPolicy", env, seed=0, policy_kwargs={"hidden_dim": 16}, device="cpu")
    policy = m.policy
    obs_list, (obs, _) = [], env.reset(seed=3)
    for _ in range(4):
        obs_list.append(obs)
        obs, *_ = env.step(GreedyAllocator().predict(obs)[0])
    obs_t = {k: th.as_tensor(np.stack([o[k] for o in obs_list])) for k in obs_list[0]}
    view = parse_obs(obs_t)
    with th.no_grad():
        dec = policy.decide(view, deterministic=False)
    alpha = th.tensor(0.3)
    out = select_losses(policy, view, dec.candidates, dec.pick_rank, alpha, 0.5)
    assert out.n > 8
    c = th.where(dec.candidates.any(1), dec.candidates.float().argmax(1), -1)
    B, M, N = dec.pick_rank.shape
    st = SelectState(view, c)
    d = policy.selector.head.embed_entities(view)
    dc, dt = policy.select_critic.embed(view), policy.select_critic_target.embed(view)
    terms: dict[str, list[th.Tensor]] = {k: [] for k in ("valid", "r", "done", "v", "actor", "q1", "q2", "h", "n")}
    for t in range(int(dec.pick_rank.max()) + 1):
        picked = dec.pick_rank == t  # (B, M, N)
        valid = picked.any(-1)
        picks = picked.float().argmax(-1)
        ts, dyn = st.features()
        mask = st.choice_mask()
        dist = MaskedCategorical(policy.selector.head(d, ts, dyn, c).unsqueeze(1).expand(B, M, N), mask)
        qs = policy.select_critic(dc, ts, dyn, c)
        qt = th.minimum(*policy.select_critic_target(dt, ts, dyn, c)).unsqueeze(1)
        min_q = th.minimum(*qs).unsqueeze(1)
        terms["v"].append((dist.probs * (qt - alpha * dist.log_probs)).sum(-1))
        terms["actor"].append((dist.probs * (alpha * dist.log_probs - min_q)).sum(-1))
        terms["q1"].append(th.gather(qs[0], 1, picks))
        terms["q2"].append(th.gather(qs[1], 1, picks))
        terms["h"].append(dist.entropy())
        terms["n"].append(mask.sum(-1).float())
        assert (mask.any(-1) | ~valid).all()  # every stored pick was a choice
        r, done = st.advance(picks, valid)
        terms["valid"].append(valid)
        terms["r"].append(r)
        terms["done"].append(done)
    stk = {k: th.stack(v) for k, v in terms.items()}
    valid = stk["valid"]
    v_next = th.cat([stk["v"][1:], th.zeros_like(stk["v"][:1])])
    y = (stk["r"] + (1 - stk["done"].float()) * v_next)[valid]
    th.testing.assert_close(out.target, y.detach(), atol=1e-5, rtol=1e-5)
    expected = 0.5 * (F.mse_loss(stk["q1"][valid], y.detach()) + F.mse_loss(stk["q2"][valid], y.detach()))
    th.testing.assert_close(out.critic_loss, expected, atol=1e-5, rtol=1e-5)
    th.testing.assert_close(out.actor_loss, stk["actor"][valid].mean(), atol=1e-5, rtol=1e-5)
    th.testing.assert_close(out.entropy, stk["h"][valid], atol=1e-5, rtol=1e-5)
    th.testing.assert_close(out.target_entropy, 0.5 * th.log(stk["n"][valid]), atol=1e-6, rtol=1e-6)


def test_team_value_closed_form_and_gradient():
    """``team_value``: V(s, a) = Σ_{j open} g(z_j) on each task's aggregate supply share, cost and size; with
    probabilities the aggregates are expectations, and the gradient reaches the probabilities."""
    from sb3_taskalloc.common.mixers import TeamValue
    from sb3_taskalloc.common.torch_layers import symlog

    env = gym.make("TaskAlloc/RBF-v0")
    obs, _ = env.reset(seed=0)
    view = parse_obs({k: th.as_tensor(v[None]) for k, v in obs.items()})
    _, N, M = view.pair_cost.shape
    K = view.supply.shape[-1]
    th.manual_seed(0)
    team = TeamValue(view.task.shape[-1], K, hidden_dim=8)
    choice = th.randint(0, M, (1, N))
    onehot = F.one_hot(choice, M).float() * view.entity_mask.unsqueeze(-1)
    expected = th.zeros(())
    for j in range(M):
        if not view.task_mask[0, j]:
            continue
        members = onehot[0, :, j].bool()
        supply = view.supply[0, members].sum(0)
        demand = view.demand[0, j]
        share = th.where(demand > 0, supply / demand.clamp_min(1e-6), th.tensor(2.0)).clamp_max(2.0)
        cost = view.pair_cost[0, members, j].sum()
        z = th.cat([view.task[0, j], share, share.min().view(1), symlog(cost).view(1), symlog(members.sum().float()).view(1)])
        expected = expected + team.g(z).squeeze()
    th.testing.assert_close(team(view, onehot)[0], expected, atol=1e-5, rtol=1e-5)
    probs = th.softmax(th.randn(1, N, M), -1).requires_grad_(True)
    team(view, probs).sum().backward()
    assert probs.grad is not None and probs.grad.abs().sum() > 0
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", policy_kwargs={"mixer_kwargs": {"team_value": True}}, device="cpu")
    assert all(isinstance(q.team, TeamValue) for q in model.critic.q_networks)
    assert (
        TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", policy_kwargs={"mixer_kwargs": {"team_value": False}})
        .critic.q_networks[0]
        .team
        is None
    )


def test_round_profit_is_the_commitment_reward():
    """The profit that the one-step improvement term reads from the observation is what the env credits when the teams
    commit (RBF's first step: no decay yet)."""
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", seed=0, device="cpu")
    env = gym.make("TaskAlloc/RBF-v0")
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        view = model.policy.parse(model.policy.obs_to_tensor(obs)[0])
        decision = model.policy.decide(view, deterministic=True)
        c = th.where(view.assignable, model.actor(view).get_actions(True), -1)
        profit = float(round_profit(model.selector.head, view, c)[0])
        _, _, _, _, info = env.step(decision.env_action[0].numpy())
        assert profit == pytest.approx(info["commitment_reward"], abs=1e-4) and profit != 0.0
