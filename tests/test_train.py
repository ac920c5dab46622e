"""Loss arithmetic of TwoStageSAC against the closed forms on hand-built batches."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import Logger
from torch.nn import functional as F

from sb3_taskalloc import TwoStageSAC
from sb3_taskalloc.baselines import GreedyAllocator
from sb3_taskalloc.common.distributions import MaskedCategorical, SegmentedCategorical, masked_pick, segment_pick
from sb3_taskalloc.common.mixers import AMIXMixer
from sb3_taskalloc.common.torch_layers import NEG, ObsView, parse_obs
from sb3_taskalloc.common.utils import foreach_polyak_update
from sb3_taskalloc.two_stage_sac import losses
from sb3_taskalloc.two_stage_sac.policies import starts_at_rule
from sb3_taskalloc.two_stage_sac.search import cover_search, select_search
from sb3_taskalloc.two_stage_sac.select_stage import SelectState, round_profit, teacher_forced
from sb3_taskalloc.two_stage_sac.updates import PreAssignUpdate, optimizer_step, optimizers, temperature


@pytest.fixture(scope="module")
def model() -> TwoStageSAC:
    m = TwoStageSAC(
        "TAMPolicy",
        "TaskAlloc/Almighty-v0",
        learning_starts=32,
        batch_size=16,
        seed=0,
        prior_coef=0.0,  # the paper's losses and critic; the prior term, the mean bonus and team_value have their own tests
        select_kwargs={"prior_coef": 0.0},
        entropy_bonus="sum",
        policy_kwargs={"hidden_dim": 16, "mixer_kwargs": {"team_value": False}, "logit_scale": 1.0, "select_logit_scale": 1.0},
        device="cpu",  # the hand-built batches below are CPU tensors
    )
    m.learn(40)
    return m


def preassign_critic_loss(
    model: TwoStageSAC, view: ObsView, next_view: ObsView, data, alpha, dones=None, gamma=None, per_entity: bool = False
):
    """The stage-1 critic loss of :class:`PreAssignUpdate` on ``data``, with its done flags, discounts (a number or one
    per row) and entropy bonus replaced where given."""
    discounts = None if gamma is None else th.as_tensor(gamma, dtype=th.float32).expand(data.rewards.shape[0]).reshape(-1, 1)
    data = data._replace(dones=data.dones if dones is None else dones.reshape(-1, 1), discounts=discounts)
    bonus, model.entropy_bonus = model.entropy_bonus, "mean" if per_entity else "sum"
    try:
        return PreAssignUpdate(model).critic_loss(view, next_view, data, alpha)
    finally:
        model.entropy_bonus = bonus


def actor_loss_of(model: TwoStageSAC, view: ObsView, alpha, dist=None, prior_coef: float = 0.0) -> th.Tensor:
    dist = model.actor(view) if dist is None else dist
    contexts = model.critic.contexts(view)
    return losses.preassign_actor_loss(dist, model.critic, contexts, view, alpha, model.policy.actor_prior, prior_coef)


def select_losses(policy, view, cand, rank, alpha, ratio, prior_coef: float = 0.0) -> losses.SelectLosses:
    out = losses.select_losses(
        policy.selector, policy.select_critic, policy.select_critic_target, view, cand, rank, policy.preassign, alpha,
        ratio, policy.selector_prior, prior_coef,
    )  # fmt: skip
    assert out is not None
    return out


def test_preassign_critic_target_and_losses(model):
    data = model.replay_buffer.sample(16)
    view, next_view = parse_obs(data.observations), parse_obs(data.next_observations)
    alpha = th.exp(model.log_ent_coef.detach())
    out = preassign_critic_loss(model, view, next_view, data, alpha)
    # Closed form: y = r + γ(1 − d)[min_k AMIX̄^k(Σ_j π_i(j|s') Q̄^k_i(s', j)) + α Σ_i H_i(s')]
    with th.no_grad():
        pi_next = model.actor(next_view)
        mixed = []
        for critic in model.critic_target.q_networks:
            q_i = (critic.scorer(next_view) * pi_next.probs).sum(-1)
            mixed.append(critic.mixer(q_i, next_view))
        h_next = -(pi_next.probs * th.log(pi_next.probs.clamp_min(1e-30))).sum((1, 2))
        y = data.rewards[:, 0] + model.gamma * (1 - data.dones[:, 0]) * (th.minimum(*mixed) + alpha * h_next)
    th.testing.assert_close(out.target_q, y, atol=1e-4, rtol=1e-4)
    c = data.candidates.transpose(1, 2).float()
    expected = 0.0
    for critic in model.critic.q_networks:
        q_tot = critic.mixer((critic.scorer(view) * c).sum(-1), view)
        expected = expected + 0.5 * ((q_tot - y) ** 2).mean()
    th.testing.assert_close(out.loss, expected, atol=1e-4, rtol=1e-4)
    # Actor: −α H(s) − min_k AMIX^k(Σ_j π Q^k)
    pi = model.actor(view)
    h = -(pi.probs * th.log(pi.probs.clamp_min(1e-30))).sum((1, 2))
    mixed_pi = [cr.mixer((cr.scorer(view) * pi.probs).sum(-1), view) for cr in model.critic.q_networks]
    th.testing.assert_close(
        actor_loss_of(model, view, alpha), (-alpha * h - th.minimum(*mixed_pi)).mean(), atol=1e-4, rtol=1e-4
    )
    # Frozen critics: the actor loss reaches the actor's parameters with the same gradient as the unfrozen formula
    # (and reusing the distribution changes nothing), and leaves no gradient on the critics.
    for net in (model.actor, model.critic):
        net.zero_grad(set_to_none=True)
    (-alpha * h - th.minimum(*mixed_pi)).mean().backward()
    expected_grads = [p.grad.clone() for p in model.actor.parameters()]
    for net in (model.actor, model.critic):
        net.zero_grad(set_to_none=True)
    actor_loss_of(model, view, alpha, model.actor(view)).backward()
    for p, g in zip(model.actor.parameters(), expected_grads, strict=True):
        th.testing.assert_close(p.grad, g, atol=1e-5, rtol=1e-4)
    assert all(p.grad is None for p in model.critic.parameters())
    assert all(p.requires_grad for p in model.critic.parameters())
    # Prior term (prior_coef β): + β Σ_i KL(π_i ‖ π₀_i), π₀ = the frozen initial actor (the actor moved away first).
    saved = {k: v.clone() for k, v in model.actor.state_dict().items()}
    try:
        with th.no_grad():
            for param in model.actor.parameters():
                param.add_(0.3 * th.randn_like(param))
        pi = model.actor(view)
        h = -(pi.probs * th.log(pi.probs.clamp_min(1e-30))).sum((1, 2))
        mixed_pi = [cr.mixer((cr.scorer(view) * pi.probs).sum(-1), view) for cr in model.critic.q_networks]
        prior = model.policy.actor_prior(view)
        kl = (pi.probs * (th.log(pi.probs.clamp_min(1e-30)) - th.log(prior.probs.clamp_min(1e-30)))).sum((1, 2))
        assert kl.max() > 1e-3, "the actor has not moved from its initial rule"
        th.testing.assert_close(
            actor_loss_of(model, view, alpha, prior_coef=0.7),
            (-alpha * h - th.minimum(*mixed_pi) + 0.7 * kl).mean(),
            atol=1e-4,
            rtol=1e-4,
        )
    finally:
        model.actor.load_state_dict(saved)
    pi = model.actor(view)
    h = -(pi.probs * th.log(pi.probs.clamp_min(1e-30))).sum((1, 2))
    # Temperature statistics: mean per-entity entropy and ratio × log(#open tasks).
    free = view.assignable
    has = free.any(1)
    stats = losses.preassign_entropy(pi, view, model.target_entropy_ratio)
    th.testing.assert_close(stats.entropy, (h / free.sum(1).clamp_min(1))[has], atol=1e-5, rtol=1e-5)
    th.testing.assert_close(
        stats.target, (model.target_entropy_ratio * th.log(view.task_mask.sum(1).float()))[has], atol=1e-6, rtol=1e-6
    )


@pytest.mark.parametrize("monotonic", [False, True])
def test_amix_closed_form(monotonic):
    th.manual_seed(1)
    mixer = AMIXMixer(entity_dim=5, task_dim=4, hidden_dim=8, monotonic=monotonic)
    B, N, M = 3, 6, 2
    ent_mask = th.tensor([[1, 1, 0, 1, 0, 1], [0] * 6, [1] * 6], dtype=th.bool)
    view = ObsView(
        entity=th.randn(B, N, 5), task=th.randn(B, M, 4), supply=th.rand(B, N, 2), demand=th.rand(B, M, 2),
        reward=th.rand(B, M), pair_cost=th.rand(B, N, M), entity_mask=ent_mask, task_mask=th.ones(B, M, dtype=th.bool),
        present=th.ones(B, N, dtype=th.bool), pair=th.zeros(B, N, M, 3),
    )  # fmt: skip
    q_i = th.randn(B, N)
    got = mixer(q_i, view)
    for b in range(B):
        mask = ent_mask[b]
        x = view.entity[b] * mask[:, None]
        k, q, v = mixer.k(x), mixer.q(x), mixer.v(x)
        scores = k @ q.T / math.sqrt(mixer.attention_dim)
        scores[:, ~mask] = -1e9
        w = th.softmax(scores, -1) @ v
        if monotonic:
            w = w.abs()
        mixed = (q_i[b][mask][:, None] * w[mask]).sum(0)
        ent_mean = view.entity[b].mean(0)
        bias = mixer.const_bias + mixer.bias(th.cat([ent_mean, view.task[b].mean(0)]))
        hidden = th.relu(mixed + bias)
        expected = hidden @ mixer.out_w.abs() + mixer.out_b if monotonic else mixer.out(hidden)
        th.testing.assert_close(got[b], expected.reshape(()), atol=1e-5, rtol=1e-5)
    # Masked entities contribute nothing.
    q_changed = q_i.clone()
    q_changed[0, 2] += 100.0
    th.testing.assert_close(mixer(q_changed, view)[0], got[0])


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


def test_entropy_coefficient_specs():
    with pytest.raises(ValueError, match="ent_coef"):
        TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", ent_coef="sometimes")
    fixed = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", ent_coef=0.05, select_kwargs={"ent_coef": "auto_0.5"})
    assert fixed.log_ent_coef is None and float(fixed.ent_coef_tensor) == pytest.approx(0.05)
    assert float(th.exp(fixed.log_select_ent_coef.detach())) == pytest.approx(0.5)


def test_learning_rate_schedule_sets_every_optimizer():
    """As in SB3's SAC, the schedule sets the learning rate of every optimizer a step runs, the temperatures' too."""
    model = TwoStageSAC(
        "TAMPolicy", "TaskAlloc/Almighty-v0", learning_rate=lambda progress: 1e-3 * progress,
        select_kwargs={"ent_coef": "auto"}, seed=0,
    )  # fmt: skip
    model.set_logger(Logger(None, []))  # silent, no log folder
    model._current_progress_remaining = 0.25
    model.train(gradient_steps=0)
    found = optimizers(model)
    assert len(found) == 6 and model.ent_coef_optimizer in found and model.select_ent_coef_optimizer in found
    assert all(group["lr"] == pytest.approx(2.5e-4) for optimizer in found for group in optimizer.param_groups)


def test_gradient_step_changes_parameters(model):
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    model.train(gradient_steps=2, batch_size=8)
    after = model.policy.state_dict()
    for prefix in ("actor.", "critic.", "selector.", "select_critic."):
        changed = [k for k in after if k.startswith(prefix) and not th.equal(before[k], after[k])]
        assert changed, f"no parameter of {prefix} changed"
    assert np.isfinite(model.logger.name_to_value["train/critic_loss"])


def _small_rbf_model(**kwargs: Any) -> TwoStageSAC:
    """A narrow RBF model whose first gradient step comes after 8 env steps, for the tests of which parts learn."""
    return TwoStageSAC(
        "TAMPolicy", "TaskAlloc/RBF-v0", learning_starts=8, batch_size=8, seed=0, policy_kwargs={"hidden_dim": 16}, **kwargs
    )


def test_frozen_preassign_actor_keeps_its_rule():
    """With ``train_preassign_actor=False`` only the select stage learns: the pre-assign actor, its temperature and its
    critics keep their values. Training those critics as well (the stage-1 update put back) would change neither the
    decisions taken nor any network that decides: the select stage's networks come out bit for bit the same."""
    m = _small_rbf_model(train_preassign_actor=False)
    assert [type(u).__name__ for u in m.updates] == ["SelectUpdate"]
    m.learn(12)
    before = {k: v.clone() for k, v in m.policy.state_dict().items()}
    alpha = float(m.log_ent_coef.detach())  # type: ignore[union-attr]
    m.train(gradient_steps=2, batch_size=8)
    after = m.policy.state_dict()

    def changed(prefix: str) -> bool:
        return any(not th.equal(before[k], after[k]) for k in after if k.startswith(prefix))

    assert changed("select_critic.") and changed("selector.")
    assert not changed("actor.") and not changed("critic.")
    assert float(m.log_ent_coef.detach()) == alpha  # type: ignore[union-attr]

    class CriticsOnly(PreAssignUpdate):  # the stage-1 critics' update alone, their target networks following
        def __call__(self, obs: ObsView, data: Any, logs: Any) -> None:
            m = self.model
            alpha = temperature(m.log_ent_coef, m.ent_coef_tensor)
            optimizer_step(m.critic.optimizer, self.critic_loss(obs, m.policy.parse(data.next_observations), data, alpha).loss)

    with_critics = _small_rbf_model(train_preassign_actor=False)  # each model seeds torch's global stream as it is made
    with_critics.updates.insert(0, CriticsOnly(with_critics))
    with_critics.learn(40)
    held = _small_rbf_model(train_preassign_actor=False).learn(40)
    trained = with_critics.policy.state_dict()
    assert any(not th.equal(trained[k], v) for k, v in held.policy.state_dict().items() if k.startswith("critic."))
    for k, v in held.policy.state_dict().items():
        if not k.startswith("critic"):
            assert th.equal(trained[k], v), k
    np.testing.assert_array_equal(with_critics.replay_buffer.actions, held.replay_buffer.actions)
    with pytest.raises(ValueError, match="train_preassign_actor"):
        TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", train_preassign_actor="no")


@pytest.mark.parametrize(
    "policy_kwargs, rule",
    [({}, True), ({"heuristic_init": False}, False), ({"encoder": "mlp"}, False), ({"pair_features": False}, False)],
)
def test_only_an_actor_that_starts_at_the_rule_can_be_held(policy_kwargs, rule):
    """Holding a pre-assign actor that starts at random weights would leave it random: it is refused by name; a policy
    without a pre-assign actor (W/o Pre) has nothing to hold."""
    small = {"hidden_dim": 16, **policy_kwargs}
    assert starts_at_rule(small) is rule
    assert TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", policy_kwargs=small).policy.preassign_rule is rule
    if rule:
        TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", train_preassign_actor=False, policy_kwargs=small)
    else:
        with pytest.raises(ValueError, match=r"starts at random ones .* set train_preassign_actor=True"):
            TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", train_preassign_actor=False, policy_kwargs=small)
    no_pre = {**small, "preassign": False}
    assert not starts_at_rule(no_pre)
    assert TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", train_preassign_actor=False, policy_kwargs=no_pre).actor is None


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


def test_foreach_polyak_update_equals_sb3():
    """The multi-tensor soft update gives exactly SB3's ``polyak_update`` and checks the parameter counts."""
    from stable_baselines3.common.utils import polyak_update

    th.manual_seed(0)
    params = [th.randn(3, 4), th.randn(7)]
    ours = [th.randn(3, 4), th.randn(7)]
    theirs = [t.clone() for t in ours]
    for _ in range(3):
        foreach_polyak_update(params, ours, 0.005)
        polyak_update(params, theirs, 0.005)
    for a, b in zip(ours, theirs, strict=True):
        th.testing.assert_close(a, b, rtol=0, atol=0)
    with pytest.raises(ValueError, match="target parameters"):
        foreach_polyak_update(params, ours[:1], 0.005)


def test_mean_entropy_bonus_in_target_and_actor(model):
    """``entropy_bonus="mean"``: the target and the actor loss use α·H̄(s), the entropy per free entity, instead of
    α·Σ_i H_i(s); the two differ exactly by the entropy term."""
    data = model.replay_buffer.sample(16)
    view, next_view = parse_obs(data.observations), parse_obs(data.next_observations)
    alpha = th.tensor(0.3)
    not_done = th.zeros_like(data.dones[:, 0])  # Almighty ends every episode: bootstrap anyway to see the bonus
    total = preassign_critic_loss(model, view, next_view, data, alpha, not_done)
    mean = preassign_critic_loss(model, view, next_view, data, alpha, not_done, per_entity=True)
    with th.no_grad():
        h = model.actor(next_view).entropy().sum(1)
    n_free = next_view.assignable.sum(1).clamp_min(1)
    discount = model.gamma
    th.testing.assert_close(total.target_q - mean.target_q, discount * alpha * (h - h / n_free), atol=1e-5, rtol=1e-5)
    assert (n_free > 1).any() and (total.target_q != mean.target_q).any()
    dist = model.actor(view)
    contexts = model.critic.contexts(view)
    plain = losses.preassign_actor_loss(dist, model.critic, contexts, view, alpha)
    per = losses.preassign_actor_loss(dist, model.critic, contexts, view, alpha, entropy_per_entity=True)
    h_now = dist.entropy().sum(1)
    expected = (-alpha * h_now / view.assignable.sum(1).clamp_min(1) + alpha * h_now).mean()
    th.testing.assert_close(per - plain, expected, atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="entropy_bonus"):
        TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", entropy_bonus="max")


def test_n_step_returns_of_the_replay_buffer():
    """``n_steps``: Σ_{k<n} γ^k r_{t+k} up to the first episode end and never past the newest stored step, with the
    observation after the last summed step and γ^k for the bootstrap (SB3's NStepReplayBuffer arithmetic)."""
    from sb3_taskalloc.common.buffers import TwoStageReplayBuffer, pack_decision

    env = gym.make("TaskAlloc/Almighty-v0")
    buf = TwoStageReplayBuffer(10, env.observation_space, env.action_space, device="cpu", n_steps=3, gamma=0.5)
    N, M = buf.n_entities, buf.n_tasks
    obs, _ = env.reset(seed=0)
    decision = pack_decision(np.zeros((1, N), np.int64), np.zeros((1, M, N), bool), -np.ones((1, M, N), np.int64))
    for t in range(6):
        marked = {k: v[None].copy() for k, v in obs.items()}
        marked["task_reward"][0, 0] = t  # identifies the stored step
        buf.add(marked, marked, decision, np.array([t + 1.0]), np.array([t == 2]), [{}])
    data = buf._get_samples(np.array([0, 1, 3, 4]))
    expected = [1 + 0.5 * 2 + 0.25 * 3, 2 + 0.5 * 3, 4 + 0.5 * 5 + 0.25 * 6, 5 + 0.5 * 6]  # episode end after step 2
    th.testing.assert_close(data.rewards[:, 0], th.tensor(expected))
    th.testing.assert_close(data.discounts[:, 0], th.tensor([0.125, 0.25, 0.125, 0.25]))
    th.testing.assert_close(data.next_observations["task_reward"][:, 0], th.tensor([2.0, 2.0, 5.0, 5.0]))
    th.testing.assert_close(data.dones[:, 0], th.tensor([1.0, 1.0, 0.0, 0.0]))
    one_step = TwoStageReplayBuffer(10, env.observation_space, env.action_space, device="cpu")
    one_step.add(marked, marked, decision, np.array([1.0]), np.array([False]), [{}])
    assert one_step._get_samples(np.array([0])).discounts is None
    with pytest.raises(ValueError, match="n_steps"):
        TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", n_steps=0)


def test_n_step_target(model):
    """The stage-1 target with per-transition discounts γ^k: y = R + (1 − terminated)·γ^k·V̄(s_{t+k})."""
    data = model.replay_buffer.sample(16)
    view, next_view = parse_obs(data.observations), parse_obs(data.next_observations)
    alpha = th.tensor(0.1)
    not_done = th.zeros_like(data.dones[:, 0])
    discounts = th.linspace(0.2, 0.9, 16)
    zero = preassign_critic_loss(model, view, next_view, data, alpha, not_done, 0.0)  # y = r
    per_row = preassign_critic_loss(model, view, next_view, data, alpha, not_done, discounts)
    full = preassign_critic_loss(model, view, next_view, data, alpha, not_done, 1.0)  # y = r + V̄(s')
    th.testing.assert_close(per_row.target_q, zero.target_q + discounts * (full.target_q - zero.target_q))


def test_reward_timing_commitment_stores_the_commitment_reward():
    """``reward_timing="commitment"`` stores ``info["commitment_reward"]`` (episode statistics keep the env reward)."""
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", reward_timing="commitment", learning_starts=200, seed=0, device="cpu")
    env = gym.make("TaskAlloc/RBF-v0")  # the same reset seed and the same uniform warm-up would be needed to replay it:
    model.learn(60)  # check instead that the stored rewards are commitment rewards, which lead the env rewards
    stored = model.replay_buffer.rewards[:60, 0]
    assert np.count_nonzero(stored) > 0
    rewards, credits = [], []
    obs, _ = env.reset(seed=0)
    for _ in range(60):
        obs, r, _, _, info = env.step(GreedyAllocator().predict(obs)[0])
        rewards.append(r)
        credits.append(info["commitment_reward"])
    assert np.flatnonzero(credits)[0] < np.flatnonzero(rewards)[0]  # RBF's teams travel: the credit leads the payment
    with pytest.raises(ValueError, match="reward_timing"):
        TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", reward_timing="arrival")


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


def reset_view(model: TwoStageSAC, env_id: str, n: int) -> ObsView:
    """The first observations of reset seeds 0 .. n − 1 of ``env_id``, parsed by ``model``'s policy as one batch."""
    env = gym.make(env_id)
    obs = [env.reset(seed=s)[0] for s in range(n)]
    return model.policy.parse(model.policy.obs_to_tensor({k: np.stack([o[k] for o in obs]) for k in obs[0]})[0])


def mt_argmax_round() -> tuple[TwoStageSAC, ObsView, th.Tensor]:
    """A small untrained MT model, 8 reset states and its argmax pre-assignment ``task_of`` on them."""
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/MT-v0", seed=0, device="cpu", policy_kwargs={"hidden_dim": 16})
    view = reset_view(model, "TaskAlloc/MT-v0", 8)
    with th.no_grad():
        return model, view, th.where(view.assignable, model.actor(view).get_actions(True), -1)


def forced_steps(head, view: ObsView, task_of: th.Tensor, rank: th.Tensor):
    """Step a :class:`SelectState` through the picks of ``rank`` (B, M, N) one at a time, the reference of the
    teacher-forced losses: yields, per step t while a task is active, (t, the state before the step's picks, the
    pointer's masked logits (B, M, N), each task's pick (B, M), which tasks pick (B, M))."""
    st, d = SelectState(view, task_of), head.embed_entities(view)
    for t in range(rank.shape[-1]):
        if not bool(st.active.any()):
            break
        task_state, dyn = st.features()
        logits = head(d, task_state, dyn, task_of).unsqueeze(1).masked_fill(~st.choice_mask(), NEG)
        hit = rank == t
        picks, valid = hit.float().argmax(-1), hit.any(-1) & st.active
        yield t, st, logits, picks, valid
        st.advance(picks, valid)


def test_select_search_loss_distils_the_best_team():
    """``select_kwargs["search_coef"]`` (implementation detail 18): per task, the search's team is at least as
    profitable as the
    deterministic one, its teacher-forced rewards add up to that profit, and the loss is −Σ_t log π(a*_t|s*_t) over the
    tasks it improves, recomputed here by stepping a :class:`SelectState` through the forced picks one at a time."""
    model, view, task_of = mt_argmax_round()
    head = model.selector.head
    B, _, M = view.pair_cost.shape
    candidates = task_of.unsqueeze(1) == th.arange(M).view(1, M, 1)
    th.manual_seed(0)
    found = select_search(head, view, task_of, samples=32, temperature=3.0)
    th.manual_seed(0)
    search = losses.select_search_loss(model.selector, view, candidates, samples=32, temperature=3.0)
    improved = found.profit > found.base
    assert bool(improved.any()), "no sampled team beat the deterministic one: the case checks nothing"
    assert bool((found.profit >= found.base).all())
    assert bool(((found.rank >= 0) <= candidates).all())  # a task picks among its own candidates only
    tf = teacher_forced(view, task_of, found.rank)
    assert tf is not None
    th.testing.assert_close(tf.reward.sum(0)[improved], found.profit[improved], atol=1e-4, rtol=1e-5)
    log_p = th.zeros(B, M)
    for _, _, logits, picks, valid in forced_steps(head, view, task_of, found.rank):
        log_p = log_p + th.where(valid, th.log_softmax(logits, -1).gather(-1, picks.unsqueeze(-1)).squeeze(-1), 0.0)
    th.testing.assert_close(search.loss, -log_p[improved].mean(), atol=1e-4, rtol=1e-5)
    has = candidates.any(-1) & view.task_mask
    assert float(search.improved) == pytest.approx(float(improved[has].float().mean()))
    assert float(search.gain) == pytest.approx(float((found.profit - found.base)[has].mean()), abs=1e-4)
    search.loss.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.selector.parameters())
    one = select_search(head, view, task_of, samples=1, temperature=3.0)
    assert bool((one.profit == one.base).all())
    assert float(losses.select_search_loss(model.selector, view, candidates, samples=1, temperature=3.0).loss) == 0.0
    bad_kwargs = ({"search_coef": -1.0}, {"search_temperature": 0.0}, {"search_samples": 0}, {"search": 1})
    for bad in bad_kwargs:
        with pytest.raises(ValueError, match=next(iter(bad))):
            TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", select_kwargs=bad)
    with pytest.raises(ValueError, match="pre-assigning policy"):
        TwoStageSAC(
            "TAMPolicy", "TaskAlloc/Almighty-v0", select_kwargs={"search_coef": 1.0}, policy_kwargs={"preassign": False}
        )
    # The term runs inside training and its statistics reach the logger.
    model = TwoStageSAC(
        "TAMPolicy", "TaskAlloc/MT-v0", select_kwargs={"search_coef": 1.0, "search_samples": 4, "batch_size": 4},
        learning_starts=30, batch_size=8, seed=0, device="cpu", policy_kwargs={"hidden_dim": 16},
    )  # fmt: skip
    model.learn(60)
    model.train(gradient_steps=1, batch_size=8)
    assert "train/select_search_improved" in model.logger.name_to_value


def test_distill_select_teaches_the_pointer_the_exact_cover():
    """:meth:`TwoStageSAC.distill_select` (implementation detail 19): its loss is −mean over the labelled tasks of the
    teacher-forced log-likelihood of their teams; DAgger fits the pointer alone, raising the likelihood of the exact
    covers of the rounds the deterministic policy meets, and is reproducible under a seed."""
    env_id = "TaskAlloc/Almighty-v0"

    def new_model() -> TwoStageSAC:
        return TwoStageSAC("TAMPolicy", env_id, seed=0, device="cpu", policy_kwargs={"hidden_dim": 16})

    model = new_model()
    view = reset_view(model, env_id, 8)
    head = model.selector.head
    rounds: list[tuple[ObsView, th.Tensor]] = []
    with th.no_grad():
        model.policy.decide(view, deterministic=True, rounds_out=rounds)
        round_view, task_of = rounds[0]
        found = cover_search(head, round_view, task_of)
    M = found.profit.shape[1]
    labelled = (task_of.unsqueeze(1) == th.arange(M).view(1, M, 1)).any(-1) & (found.profit > 0)
    assert bool(labelled.any()), "no task labelled: the case checks nothing"
    log_p = losses.team_log_prob(head, round_view, task_of, found.rank)
    assert log_p is not None
    before = losses.cover_imitation_loss(head, round_view, task_of, found.rank, labelled)
    th.testing.assert_close(before, -log_p[labelled].mean())
    assert float(losses.cover_imitation_loss(head, round_view, task_of, found.rank, th.zeros_like(labelled))) == 0.0
    frozen = {n: p.detach().clone() for n, p in model.policy.named_parameters() if not n.startswith("selector.")}
    pointer = {n: p.detach().clone() for n, p in model.policy.named_parameters() if n.startswith("selector.")}
    history = model.distill_select(env_id, iterations=2, episodes=8, epochs=4, seed=0)
    assert [h["iteration"] for h in history] == [1.0, 2.0]
    for h in history:
        assert h["steps"] == 8 and h["rounds"] >= 8 and h["labelled_tasks"] > 0 and 0.0 <= h["improved"] <= 1.0
        assert h["gain"] >= -1e-6 and math.isfinite(h["loss"])  # the cover is never worse than the decode
    for name, p in model.policy.named_parameters():
        if name in frozen:
            assert th.equal(p, frozen[name]), f"{name} changed: only the pointer learns"
    assert any(not th.equal(p, pointer[n]) for n, p in model.policy.named_parameters() if n in pointer)
    after = losses.cover_imitation_loss(head, round_view, task_of, found.rank, labelled)
    assert float(after.detach()) < float(before.detach())
    assert new_model().distill_select(env_id, iterations=2, episodes=8, epochs=4, seed=0) == history
    seen: list[dict[str, float]] = []

    def stop_after_one(stats: dict[str, float]) -> bool:  # a callback sees each iteration's figures; False stops there
        seen.append(stats)
        return False

    stopped = new_model().distill_select(env_id, iterations=3, episodes=8, epochs=4, seed=0, callback=stop_after_one)
    assert stopped == seen == history[:1]
    assert len(new_model().distill_select(env_id, iterations=1, episodes=4, epochs=2, imitation="set", seed=0)) == 1
    # On a VecEnv the copies decide in one batch; episodes are counted over all of them.
    (vec,) = new_model().distill_select(make_vec_env(env_id, n_envs=3), iterations=1, episodes=4, epochs=1, seed=0)
    assert vec["steps"] == 6 and vec["rounds"] >= 6  # two batched steps of 3 one-step episodes
    bad_arguments = ({"iterations": 0}, {"episodes": 0}, {"epochs": 1.5}, {"batch_size": 0}, {"learning_rate": 0.0})
    for bad in (*bad_arguments, {"imitation": "team"}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            model.distill_select(env_id, **bad)  # type: ignore[arg-type]
    pooled = TwoStageSAC("TAMPolicy", env_id, device="cpu", policy_kwargs={"preassign": False, "hidden_dim": 16})
    with pytest.raises(ValueError, match="pre-assigning policy"):
        pooled.distill_select(env_id)


def test_cover_imitation_loss_as_a_set():
    """``imitation="set"``: at each step of the labelled order the loss takes the probability of picking any member of
    the cover not picked yet, recomputed here by stepping a :class:`SelectState` through the labelled picks; it is never
    above the sequence loss, which takes the labelled pick's own probability."""
    model, round_view, task_of = mt_argmax_round()
    head = model.selector.head
    B, _, M = round_view.pair_cost.shape
    with th.no_grad():
        found = cover_search(head, round_view, task_of)
    labelled = (task_of.unsqueeze(1) == th.arange(M).view(1, M, 1)).any(-1) & (found.profit > 0)
    assert bool((((found.rank >= 0).sum(-1) > 1) & labelled).any()), "no labelled team of two or more: the set is the pick"
    before = losses.cover_imitation_loss(head, round_view, task_of, found.rank, labelled)
    # As a set: at each step of the labelled order, the probability of any member not picked yet, recomputed by stepping
    # a SelectState through the labelled picks; never below the labelled pick's own probability.
    as_set = losses.cover_imitation_loss(head, round_view, task_of, found.rank, labelled, as_set=True)
    set_log_p = th.zeros(B, M)
    for t, st, logits, _, valid in forced_steps(head, round_view, task_of, found.rank):
        remaining = (found.rank >= t) & st.choice_mask()
        p_set = (th.softmax(logits, -1) * remaining.float()).sum(-1)
        set_log_p = set_log_p + th.where(valid, p_set.clamp_min(1e-12).log(), 0.0)
    th.testing.assert_close(as_set, -set_log_p[labelled].mean(), atol=1e-4, rtol=1e-5)
    assert float(as_set.detach()) <= float(before.detach()) + 1e-6
    assert float(losses.cover_imitation_loss(head, round_view, task_of, found.rank, th.zeros_like(labelled), True)) == 0.0


def _almighty() -> gym.Env:
    import envs  # noqa: F401  (a subprocess registers the ids itself)

    return gym.make("TaskAlloc/Almighty-v0")
