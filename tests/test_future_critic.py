"""The future critic Q = P + F (``TAMPolicy(mixer="future")``): the exact step profit P against the env's commitment
reward, team by team; its update's target against its closed form, with the pre-assign actor held; the value-aware
decoder against an enumeration."""

from __future__ import annotations

import itertools
import json
from unittest.mock import patch

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from torch.nn import functional as F

from sb3_taskalloc import TwoStageSAC
from sb3_taskalloc.common.policies import FutureCritic, executed_assignment, executed_profit
from sb3_taskalloc.common.torch_layers import ObsView
from sb3_taskalloc.experiments.bench.policy import decoder_rows
from sb3_taskalloc.two_stage_sac.decoding import (
    ARGMAX,
    decide_preassigned,
    future_pair_values,
    get_decoding_strategy,
    value_aware_view,
)
from sb3_taskalloc.two_stage_sac.search import cover_search, exact_covers
from sb3_taskalloc.two_stage_sac.updates import FutureCriticUpdate


def team_by_team(obs: dict[str, np.ndarray], action: np.ndarray) -> float:
    """Σ over the tasks the action serves of (reward − Σ its members' pair costs), by loops over the env action."""
    M = obs["task_reward"].shape[0]
    profit = 0.0
    for j in range(M):
        members = np.flatnonzero(action == j)
        if len(members):
            profit += float(obs["task_reward"][j]) - float(obs["pair_cost"][members, j].sum())
    return profit


@pytest.mark.parametrize("env_id", ["TaskAlloc/MT-v0", "TaskAlloc/EPT-v0", "TaskAlloc/RBF-v0"])
def test_the_step_profit_is_the_commitment_reward_team_by_team(env_id: str) -> None:
    """P(s, a) recomputed team by team equals ``executed_profit``; it is the commitment reward of every step on MT and
    EPT, and of the first step on RBF (later RBF steps also settle the decay of teams still travelling)."""
    model = TwoStageSAC(
        "TAMPolicy", env_id, policy_kwargs={"mixer": "future"}, train_preassign_actor=False, seed=0, device="cpu"
    )
    env = gym.make(env_id)
    served = 0
    for seed in range(2):
        obs, _ = env.reset(seed=seed)
        for t in range(25):
            with th.no_grad():
                view = model.policy.parse(model.policy.obs_to_tensor(obs)[0])
                decision = model.policy.decide(view, deterministic=False)
            action = decision.env_action[0].numpy()
            profit = float(executed_profit(view, decision.env_action)[0])
            assert profit == pytest.approx(team_by_team(obs, action), rel=1e-5, abs=1e-4)
            served += int((action < len(obs["task_reward"])).any())
            obs, _, terminated, truncated, info = env.step(action)
            if t == 0 or env_id != "TaskAlloc/RBF-v0":
                assert info["commitment_reward"] == pytest.approx(profit, rel=1e-5, abs=1e-4)
            if terminated or truncated:
                break
    assert served > 0  # some step sent a team, so the comparison covered a non-zero profit


def small_future_model() -> TwoStageSAC:
    """MT with the future critic and the pre-assign actor held, small enough to train in seconds."""
    return TwoStageSAC(
        "TAMPolicy",
        "TaskAlloc/MT-v0",
        policy_kwargs={"mixer": "future", "hidden_dim": 16},
        train_preassign_actor=False,
        learning_starts=40,
        batch_size=16,
        buffer_size=1000,
        seed=0,
        device="cpu",
    )


@pytest.fixture(scope="module")
def future_model() -> TwoStageSAC:
    return small_future_model().learn(60)


def test_the_future_critic_is_chosen_by_name_and_trains_with_the_actor_held() -> None:
    model = small_future_model()
    assert all(isinstance(q, FutureCritic) for q in model.critic.q_networks)
    assert isinstance(model.updates[0], FutureCriticUpdate)
    actor = [p.detach().clone() for p in model.actor.parameters()]
    critic = [p.detach().clone() for p in model.critic.parameters()]
    model.learn(60)
    assert np.isfinite(model.logger.name_to_value["train/critic_loss"])
    assert "train/actor_loss" not in model.logger.name_to_value
    assert all(th.equal(a, p) for a, p in zip(actor, model.actor.parameters(), strict=True))  # held at its rule
    assert any(not th.equal(c, p) for c, p in zip(critic, model.critic.parameters(), strict=True))  # F learns
    with pytest.raises(ValueError, match="train_preassign_actor=False"):
        TwoStageSAC("TAMPolicy", "TaskAlloc/MT-v0", policy_kwargs={"mixer": "future", "hidden_dim": 16}, device="cpu")


def test_the_future_critics_value_is_the_profit_plus_the_mixed_future(future_model: TwoStageSAC) -> None:
    data = future_model.replay_buffer.sample(16)
    view = future_model.policy.parse(data.observations)
    actions = data.actions.long()
    with th.no_grad():
        values = future_model.critic.decision_values(view, data.candidates, actions)
        for q, critic in zip(values, future_model.critic.q_networks, strict=True):
            future = critic(view, executed_assignment(actions, view.reward.shape[1]))
            th.testing.assert_close(q, executed_profit(view, actions) + future)
    assert not th.equal(values[0], values[1])  # two critics, two values


def test_the_future_value_is_linear_in_the_assignment(future_model: TwoStageSAC) -> None:
    """Each F^k(s, a) − F^k(s, 0) is Σ_ij a_ij g^k_ij for any assignment a: the per-pair values the value-aware
    decoder adds to the profit are the critic's whole dependence on the assignment."""
    data = future_model.replay_buffer.sample(16)
    view = future_model.policy.parse(data.observations)
    B, N, M = view.pair_cost.shape
    a = executed_assignment(th.randint(0, M + 1, (B, N)), M) * view.valid
    for critic in future_model.critic.q_networks:
        zero = th.zeros_like(view.pair_cost, requires_grad=True)
        ctx = critic.context(view)
        (g,) = th.autograd.grad(critic.mix(ctx, zero).sum(), zero)
        with th.no_grad():
            th.testing.assert_close(critic.mix(ctx, a) - critic.mix(ctx, zero), (a * g).sum((1, 2)), rtol=1e-4, atol=1e-4)
        assert critic.team is None


def test_the_future_critics_target_is_the_return_less_the_step_profit(future_model: TwoStageSAC) -> None:
    """F^k(s, a) → r − P(s, a) + γ(1 − d)·[P(s′, a′) + min_k F̄^k(s′, a′)] with a′ the argmax decision at s′."""
    m = future_model
    data = m.replay_buffer.sample(16)
    view, next_view = m.policy.parse(data.observations), m.policy.parse(data.next_observations)
    dones = th.tensor([0.0, 1.0] * 8)
    data = data._replace(dones=dones.reshape(-1, 1))
    alpha = th.tensor(0.3)
    with th.no_grad():
        out = m.updates[0].critic_loss(view, next_view, data, alpha)
        actions = data.actions.long()
        nxt = decide_preassigned(m.policy, next_view, ARGMAX)
        M = view.reward.shape[1]
        next_q = th.stack(
            [
                executed_profit(next_view, nxt.env_action) + q(next_view, executed_assignment(nxt.env_action, M))
                for q in m.critic_target.q_networks
            ]
        ).min(0)
        profit = executed_profit(view, actions)
        target_f = data.rewards.squeeze(-1) - profit + (1 - dones) * m.gamma * next_q.values
        futures = [q(view, executed_assignment(actions, M)) for q in m.critic.q_networks]
    th.testing.assert_close(out.target_q, target_f + profit)
    th.testing.assert_close(out.loss, 0.5 * sum(F.mse_loss(f, target_f) for f in futures))
    for current, f in zip(out.current, futures, strict=True):
        th.testing.assert_close(current, f + profit)


def brute_force_best(view: ObsView, b: int, entities: np.ndarray, cost: np.ndarray) -> float:
    """The most profitable assignment of ``entities`` to the open tasks of state ``b`` (or to none), where a task counts
    only if its team covers its demand: Σ_j (r_j − Σ_{i ∈ team j} cost_ij), by enumerating every assignment."""
    tasks = np.flatnonzero(view.task_mask[b].numpy())
    supply, demand, reward = view.supply[b].numpy(), view.demand[b].numpy(), view.reward[b].numpy()
    best = 0.0
    for choice in itertools.product(range(len(tasks) + 1), repeat=len(entities)):
        total, feasible = 0.0, True
        for k, j in enumerate(tasks):
            team = entities[np.asarray(choice) == k]
            if len(team) == 0:
                continue
            if (supply[team].sum(0) < demand[j] - 1e-6).any():
                feasible = False
                break
            total += float(reward[j]) - float(cost[team, j].sum())
        if feasible:
            best = max(best, total)
    return best


def visited_states(model: TwoStageSAC, steps: int = 12) -> tuple[list[dict[str, np.ndarray]], ObsView]:
    """The states of ``steps`` deterministic MT steps from reset seed 5, and their batch's view."""
    env = gym.make("TaskAlloc/MT-v0")
    obs, _ = env.reset(seed=5)
    states = []
    for _ in range(steps):
        states.append(obs)
        obs = env.step(model.predict(obs, deterministic=True)[0])[0]
    policy = model.policy
    return states, policy.parse(policy.obs_to_tensor({k: np.stack([o[k] for o in states]) for k in states[0]})[0])


@pytest.mark.parametrize("name", ["exact_top", "value_top"])
def test_an_exact_top_round_keeps_its_covers_teams(future_model: TwoStageSAC, name: str) -> None:
    """The exact cover of a round's candidate pairs is the candidates themselves (each team of the round's cover is the
    most profitable of its own members), which is why its teams do not solve it again; and the teams equal those of
    the search that does."""
    policy = future_model.policy
    _, view = visited_states(future_model)
    decoder = get_decoding_strategy(name, top=2)
    visited: list[tuple[ObsView, th.Tensor]] = []
    with th.no_grad():
        decide_preassigned(policy, view, decoder, visited)
        for round_view, task_of in visited:
            scored = value_aware_view(policy, round_view) if name == "value_top" else round_view
            M = round_view.task_mask.shape[1]
            allowed = task_of.unsqueeze(-1) == th.arange(M)
            assert th.equal(exact_covers(scored, allowed), task_of)
            rank, kept = decoder.teams(policy, round_view, task_of)
            if name == "exact_top":
                solved = cover_search(policy.selector.head, round_view, task_of)
                assert th.equal(rank, solved.rank) and th.equal(kept, solved.profit > 0)
    assert sum(int((c >= 0).sum()) for _, c in visited) >= 10


def test_the_value_aware_decoder_maximises_profit_plus_future_value(future_model: TwoStageSAC) -> None:
    """With every pair allowed (``top`` = M) the value-aware decoder's first round is worth, by r − (c − g)⁺, the best
    of all assignments enumerated; with g = 0 it decides as ``exact_top`` of the same ``top``; the policy of another
    critic is refused."""
    policy = future_model.policy
    states, view = visited_states(future_model)
    # Five free trucks per state keep the enumeration small: (M + 1)^5 assignments.
    view = view._replace(entity_mask=view.entity_mask & (view.entity_mask.cumsum(-1) <= 5))
    M = view.reward.shape[1]
    with th.no_grad():
        g = future_pair_values(policy, view)
        assert bool((g[~view.valid] == 0).all()) and bool((g[view.valid] != 0).any())
        adjusted = (view.pair_cost - g).clamp_min(0.0)
        with future_model.decoding("value_top", top=M):
            first = decide_preassigned(policy, view, policy.decoder)
        team = (first.pick_rank >= 0) & first.kept.unsqueeze(-1)  # (B, M, N)
        found = (first.kept * (view.reward - (team.float() * adjusted.transpose(1, 2)).sum(-1))).sum(-1)
    checked = 0
    for b in range(view.reward.shape[0]):
        entities = np.flatnonzero(view.entity_mask[b].numpy())
        if len(entities) == 0 or not bool(view.task_mask[b].any()):
            continue
        assert float(found[b]) == pytest.approx(brute_force_best(view, b, entities, adjusted[b].numpy()), abs=1e-3)
        checked += 1
    assert checked >= 3
    rounds: list[ObsView] = []
    visited: list[tuple[ObsView, th.Tensor]] = []

    def zero(_: object, v: ObsView) -> th.Tensor:
        rounds.append(v)
        return th.zeros_like(v.pair_cost)

    with th.no_grad(), patch("sb3_taskalloc.two_stage_sac.decoding.future_pair_values", zero):
        no_future = decide_preassigned(policy, view, get_decoding_strategy("value_top", top=2), visited)
        exact = decide_preassigned(policy, view, get_decoding_strategy("exact_top", top=2))
    assert th.equal(no_future.env_action, exact.env_action)
    # F's per-pair values are computed once per round, for the round's pre-assignment and teams alike
    assert len(rounds) == len(visited) >= 1
    paper = TwoStageSAC("TAMPolicy", "TaskAlloc/MT-v0", policy_kwargs={"hidden_dim": 16}, device="cpu")
    with pytest.raises(ValueError, match="mixer='future'"):
        paper.predict(states[0], deterministic=True, decoder="value_top")
    # the decision-time benchmark times value_top for a model with the future critic only
    assert "value_top" in [row[0] for row in decoder_rows(future_model)]
    assert "value_top" not in [row[0] for row in decoder_rows(paper)]


def test_the_diagnosis_reads_the_future_critic_with_the_actor_held(future_model: TwoStageSAC) -> None:
    """The held actor's future critic trains, so the diagnosis (and the learning experiment) report its figures; a held
    actor with the paper's critic, which does not train, has none."""
    from sb3_taskalloc.experiments.diagnose import diagnose

    assert np.isfinite(diagnose(future_model, "TaskAlloc/MT-v0", episodes=1, branches=0).q_corr)
    held = TwoStageSAC("TAMPolicy", "TaskAlloc/MT-v0", policy_kwargs={"hidden_dim": 16}, train_preassign_actor=False)
    assert np.isnan(diagnose(held, "TaskAlloc/MT-v0", episodes=1, branches=0).q_corr)


def test_the_learning_experiment_trains_and_reevaluates_the_future_critic(tmp_path) -> None:
    """The learning experiment with the future critic and the actor held: the report reads the critic (it trains), and
    the saved models are evaluated again by ``value_top``, their untrained twins built with the actor held too."""
    from sb3_taskalloc.experiments import learn

    kwargs = {"learning_starts": 2, "batch_size": 4, "train_preassign_actor": False}
    kwargs["policy_kwargs"] = {"hidden_dim": 8, "mixer": "future"}
    run = learn.LearnRun("Almighty", 1, steps=6, eval_episodes=2, eval_every=3, algo_kwargs=kwargs, planners=(),
                         out=tmp_path, select_dagger=0)  # fmt: skip
    text = run.run(progress=False).read_text()
    assert "- critic: not trained" not in text and "corr(Q, G)" in text
    searched = run.reevaluate(decoder="value_top", decoder_kwargs={"top": 2})
    assert searched.name == "Almighty_decoder_value_top_top_2.md"
    rows = json.loads(searched.with_suffix(".json").read_text())["seeds"]
    assert len(rows[0]["trained"]) == len(rows[0]["untrained"]) == 2


def test_the_surcharge_is_value_top_with_uniform_negative_pair_values(future_model: TwoStageSAC) -> None:
    """``exact_top(surcharge=σ)`` decides as ``value_top`` whose pair values are g = −σ·c on every valid pair: the
    setting is the measured replacement of the learned values (docs/learning.md)."""
    policy = future_model.policy
    _, view = visited_states(future_model)
    sigma = 0.5  # large enough that the surcharge moves some decision of these states

    def surcharge(_: object, v: ObsView) -> th.Tensor:
        return -sigma * v.pair_cost * v.valid

    with th.no_grad():
        with patch("sb3_taskalloc.two_stage_sac.decoding.future_pair_values", surcharge):
            uniform = decide_preassigned(policy, view, get_decoding_strategy("value_top", top=2))
        surcharged = decide_preassigned(policy, view, get_decoding_strategy("exact_top", top=2, surcharge=sigma))
        plain = decide_preassigned(policy, view, get_decoding_strategy("exact_top", top=2))
    assert th.equal(uniform.env_action, surcharged.env_action)
    assert th.equal(uniform.pick_rank, surcharged.pick_rank)
    assert not th.equal(surcharged.env_action, plain.env_action)
