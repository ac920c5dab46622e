"""Loss arithmetic of TwoStageSAC against the closed forms on hand-built batches: the pre-assignment's critic and actor,
the entropy terms, n-step targets, the schedules and the target networks (the pointer's: ``test_select_losses.py``)."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.logger import Logger

from sb3_taskalloc import TwoStageSAC
from sb3_taskalloc.baselines import GreedyAllocator
from sb3_taskalloc.common.mixers import AMIXMixer
from sb3_taskalloc.common.torch_layers import ObsView, parse_obs
from sb3_taskalloc.common.utils import foreach_polyak_update
from sb3_taskalloc.two_stage_sac import losses
from sb3_taskalloc.two_stage_sac.policies import starts_at_rule
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
