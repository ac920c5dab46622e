"""TAMPolicy: masks, NaN safety, permutation equivariance, padding invariance."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.utils import obs_as_tensor

from envs.rendering import random_valid_action
from sb3_taskalloc import TAMPolicy
from sb3_taskalloc.common.torch_layers import ObsView, parse_obs
from sb3_taskalloc.two_stage_sac.decoding import get_decoding_strategy
from sb3_taskalloc.two_stage_sac.select_stage import Decision, SelectState, select_features

VARIANTS = {
    "full": {},
    "wo_pre_seq": {"preassign": False},
    "wo_pre_random": {"preassign": False, "task_order": "random"},
    "wo_tam": {"encoder": "mlp"},
    "wo_amix": {"mixer": "global"},
    "attention_monotonic": {"n_attention_layers": 1, "mixer_kwargs": {"monotonic": True}},
    "rounds": {"rounds": 3},
}
ENVS = ["TaskAlloc/Almighty-v0", "TaskAlloc/EPT-v0", "TaskAlloc/RBF-v0", "TaskAlloc/MT-v0"]


def make_policy(env: gym.Env, decoder: str = "argmax", decoder_kwargs: dict | None = None, **kwargs) -> TAMPolicy:
    """A narrow TAMPolicy whose deterministic decisions are decoded by the strategy ``decoder``."""
    space = env.observation_space
    policy = TAMPolicy(space, env.action_space, lambda _: 1e-3, hidden_dim=16, **kwargs)  # type: ignore[arg-type]
    policy.decoder = get_decoding_strategy(decoder, **(decoder_kwargs or {}))
    return policy


def sample_observations(env_id: str, n: int, seed: int = 0) -> list[dict[str, np.ndarray]]:
    env = gym.make(env_id)
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    out = [obs]
    while len(out) < n:
        obs, _, term, trunc, _ = env.step(random_valid_action(obs, rng))
        out.append(obs)
        if term or trunc:
            obs, _ = env.reset(seed=int(rng.integers(1 << 30)))
            out.append(obs)
    return out[:n]


def batch(observations: list[dict[str, np.ndarray]]) -> dict[str, th.Tensor]:
    return obs_as_tensor({k: np.stack([o[k] for o in observations]) for k in observations[0]}, th.device("cpu"))  # type: ignore[return-value]


@pytest.mark.parametrize("env_id", ENVS)
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_actions_respect_masks(env_id, variant):
    th.manual_seed(0)
    env = gym.make(env_id)
    policy = make_policy(env, **VARIANTS[variant])
    observations = sample_observations(env_id, 24)
    view = parse_obs(batch(observations))
    M = env.unwrapped.max_tasks  # type: ignore[attr-defined]
    for deterministic in (True, False):
        for _ in range(3):
            d = policy.decide(view, deterministic=deterministic)
            action = d.env_action.numpy()
            for b, obs in enumerate(observations):
                mask = obs["action_mask"].reshape(len(action[b]), M + 1).astype(bool)
                assert mask[np.arange(len(action[b])), action[b]].all(), "an action broke the mask"
            # Candidates are free entities and open tasks; every kept task is covered by its picks.
            cand = d.candidates.numpy()
            assert not (cand & ~view.entity_mask.numpy()[:, None, :]).any()
            assert not (cand & ~view.task_mask.numpy()[:, :, None]).any()
            picked = (d.pick_rank >= 0) & d.kept.unsqueeze(-1)
            supplied = (picked.float() @ view.supply).numpy()
            assert (supplied >= view.demand.numpy() - 1e-4)[d.kept.numpy()].all()
            # The env accepts the action with no invalid assignment.
    env.reset(seed=0)
    act, _ = policy.predict(observations[0], deterministic=True)
    assert act.shape == env.action_space.shape


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_all_masked_rows_no_nan(variant):
    env = gym.make("TaskAlloc/RBF-v0")
    policy = make_policy(env, **VARIANTS[variant])
    obs = sample_observations("TaskAlloc/RBF-v0", 2)
    no_entities = {k: v.copy() for k, v in obs[0].items()}
    no_entities["entity_mask"][:] = 0
    no_tasks = {k: v.copy() for k, v in obs[1].items()}
    no_tasks["task_mask"][:] = 0
    view = parse_obs(batch([no_entities, no_tasks]))
    d = policy.decide(view, deterministic=False)
    assert (d.env_action == env.unwrapped.max_tasks).all()  # type: ignore[attr-defined]
    if policy.actor is not None and policy.critic is not None:
        dist = policy.actor(view)
        assert th.isfinite(dist.entropy()).all() and th.isfinite(dist.probs).all()
        for q in policy.critic(view, dist.probs):
            assert th.isfinite(q).all()


def permute(obs: dict[str, np.ndarray], perm_e: np.ndarray, perm_t: np.ndarray) -> dict[str, np.ndarray]:
    N, M = len(perm_e), len(perm_t)
    out = dict(obs)
    for key in ("entity_features", "entity_supply", "entity_mask"):
        out[key] = obs[key][perm_e]
    for key in ("task_features", "task_demand", "task_reward", "task_mask"):
        out[key] = obs[key][perm_t]
    out["pair_cost"] = obs["pair_cost"][perm_e][:, perm_t]
    mask = obs["action_mask"].reshape(N, M + 1)
    out["action_mask"] = np.concatenate([mask[perm_e][:, perm_t], mask[perm_e][:, M:]], 1).reshape(-1)
    return out


@pytest.mark.parametrize("kwargs", [{}, {"n_attention_layers": 1}, {"mixer_kwargs": {"monotonic": True}}])
def test_permutation_equivariance(kwargs):
    th.manual_seed(0)
    env = gym.make("TaskAlloc/RBF-v0")
    policy = make_policy(env, **kwargs)
    obs = sample_observations("TaskAlloc/RBF-v0", 12)[-1]
    rng = np.random.default_rng(0)
    pe, pt = rng.permutation(len(obs["entity_mask"])), rng.permutation(len(obs["task_mask"]))
    v1, v2 = parse_obs(batch([obs])), parse_obs(batch([permute(obs, pe, pt)]))
    assert policy.actor is not None and policy.critic is not None
    p1, p2 = policy.actor(v1).probs[0], policy.actor(v2).probs[0]
    th.testing.assert_close(p1[pe][:, pt], p2, atol=1e-5, rtol=1e-5)
    q1 = policy.critic.q_networks[0].scorer(v1)[0]  # type: ignore[index]
    q2 = policy.critic.q_networks[0].scorer(v2)[0]  # type: ignore[index]
    th.testing.assert_close(q1[pe][:, pt], q2, atol=1e-5, rtol=1e-5)
    for a, b in zip(policy.critic(v1, policy.actor(v1).probs), policy.critic(v2, policy.actor(v2).probs), strict=True):
        th.testing.assert_close(a, b, atol=1e-4, rtol=1e-5)  # Q_tot is invariant


def test_padding_changes_nothing():
    th.manual_seed(0)
    small = gym.make("TaskAlloc/RBF-v0")
    big = gym.make("TaskAlloc/RBF-v0", max_entities=140, max_tasks=14)
    policy = make_policy(small, n_attention_layers=1)
    o_small, _ = small.reset(seed=3)
    o_big, _ = big.reset(seed=3)
    v_small, v_big = parse_obs(batch([o_small])), parse_obs(batch([o_big]))
    assert policy.actor is not None and policy.critic is not None
    p_small, p_big = policy.actor(v_small).probs[0], policy.actor(v_big).probs[0]
    th.testing.assert_close(p_big[:100, :10], p_small, atol=1e-5, rtol=1e-5)
    assert p_big[100:].abs().sum() == 0 and p_big[:, 10:].abs().sum() == 0
    for a, b in zip(
        policy.critic(v_small, policy.actor(v_small).probs), policy.critic(v_big, policy.actor(v_big).probs), strict=True
    ):
        th.testing.assert_close(a, b, atol=1e-4, rtol=1e-5)
    # Deterministic decisions agree on the real entities; padded ones stay unassigned.
    a_small = policy.decide(v_small, deterministic=True).env_action[0]
    a_big = policy.decide(v_big, deterministic=True).env_action[0]
    assert th.equal(th.where(a_big[:100] == 14, 10, a_big[:100]), a_small) and (a_big[100:] == 14).all()


def test_bad_spaces_rejected():
    env = gym.make("CartPole-v1")
    with pytest.raises(ValueError, match="TaskAlloc Dict observation space"):
        TAMPolicy(env.observation_space, env.action_space, lambda _: 1e-3)  # type: ignore[arg-type]
    rbf = gym.make("TaskAlloc/RBF-v0")
    with pytest.raises(ValueError, match="encoder"):
        make_policy(rbf, encoder="cnn")
    with pytest.raises(ValueError, match="mixer"):
        make_policy(rbf, mixer="qmix")
    with pytest.raises(ValueError, match="task_order"):
        make_policy(rbf, preassign=False, task_order="shuffled")


def test_options_that_do_not_apply_are_refused():
    """``task_order`` orders the tasks of the shared pool: with pre-assignment there is no order to choose."""
    rbf = gym.make("TaskAlloc/RBF-v0")
    for order in ("sequential", "random"):
        with pytest.raises(ValueError, match="only without pre-assignment"):
            make_policy(rbf, task_order=order)
    assert make_policy(rbf, preassign=False).task_order == "sequential"


def test_rounds_give_the_left_over_entities_the_untried_tasks():
    """Every entity's cheapest task (0) needs more than all of them supply, so its candidates fall short and nobody is
    sent. A second round offers the same entities the tasks not tried yet: task 1 gets the team its pointer rule picks
    (entity 2, the lowest cost per unit). The decision the losses learn from stays the first round's."""
    env = gym.make("TaskAlloc/Almighty-v0", n_skills=1, specialists=2)  # K = 1, N = 3, M = 2 (only its spaces)
    supply = th.tensor([[[1.0], [1.0], [2.0]]])
    pc = th.tensor([[[1.0, 2.0], [1.0, 2.0], [1.0, 2.0]]])
    obs = {
        "entity_features": th.cat([pc[..., :1], supply, th.zeros(1, 3, 4)], -1),
        "task_features": th.tensor([[[100.0, 10.0, 0, 0, 0], [10.0, 2.0, 0, 0, 0]]]),
        "entity_supply": supply, "task_demand": th.tensor([[[10.0], [2.0]]]), "task_reward": th.tensor([[100.0, 10.0]]),
        "pair_cost": pc, "entity_mask": th.ones(1, 3, dtype=th.int8), "task_mask": th.ones(1, 2, dtype=th.int8),
    }  # fmt: skip
    view = parse_obs(obs)
    one, two = make_policy(env), make_policy(env, rounds=2)
    two.load_state_dict(one.state_dict())
    first, both = one.decide(view, deterministic=True), two.decide(view, deterministic=True)
    assert first.candidates[0, 0].all() and not first.kept.any()  # everybody chose task 0, which nobody can cover
    assert first.env_action.tolist() == [[2, 2, 2]]
    assert both.env_action.tolist() == [[2, 2, 1]]
    for field in ("candidates", "pick_rank", "kept"):
        assert th.equal(getattr(both, field), getattr(first, field))
    rounds: list = []  # the states the select stage decoded: the second round sees task 1 alone
    assert th.equal(two.decide(view, deterministic=True, rounds_out=rounds).env_action, both.env_action)
    assert [task_of.tolist() for _, task_of in rounds] == [[[0, 0, 0]], [[1, 1, 1]]]
    assert rounds[0][0] is view and rounds[1][0].task_mask.tolist() == [[False, True]]
    with pytest.raises(ValueError, match="rounds_out needs a pre-assigning policy"):
        make_policy(env, preassign=False).decide(view, deterministic=True, rounds_out=[])
    with pytest.raises(ValueError, match="rounds must be a positive integer"):
        make_policy(env, rounds=0)
    pooled = make_policy(env, rounds=2, preassign=False)  # tasks pick in turn from one pool: rounds do not apply
    assert pooled.decide(view, deterministic=True).env_action.tolist() == [[2, 2, 1]]


def test_preassign_search_takes_the_most_profitable_first_round():
    """With the ``preassign_search`` decoder of K samples a deterministic decision's first round is the best, by the
    step's profit, of the argmax
    and K − 1 pre-assignments from the policy's own stream (seeded at 0, so decisions are reproducible): never less
    profitable than the argmax, more in some of these RBF states; K = 1 is the argmax."""
    from sb3_taskalloc.two_stage_sac.select_stage import round_profit

    env = gym.make("TaskAlloc/RBF-v0")
    obs = [env.reset(seed=s)[0] for s in range(6)]
    view = parse_obs(obs_as_tensor({k: np.stack([o[k] for o in obs]) for k in obs[0]}, th.device("cpu")))
    plain, searching, again = (make_policy(env, "preassign_search", {"samples": k}) for k in (1, 16, 16))
    searching.load_state_dict(plain.state_dict())
    again.load_state_dict(plain.state_dict())
    with th.no_grad():
        argmax, best = plain.decide(view, deterministic=True), searching.decide(view, deterministic=True)
        c = th.where(view.assignable, plain.actor(view).get_actions(True), -1)
        M = view.task_mask.shape[1]
        assert th.equal(argmax.candidates, c.unsqueeze(1) == th.arange(M).view(1, M, 1))
        task_of = th.where(best.candidates.any(1), best.candidates.float().argmax(1), -1)
        base, found = round_profit(plain.selector.head, view, c), round_profit(plain.selector.head, view, task_of)
        assert bool((found >= base - 1e-5).all()) and bool((found > base + 1e-5).any())
        assert th.equal(again.decide(view, deterministic=True).env_action, best.env_action)
    for bad in ({"samples": 0}, {"temperature": 0.0}, {"top": 2}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            get_decoding_strategy("preassign_search", **bad)


def episode_view(env: gym.Env, policy: TAMPolicy) -> ObsView:
    """Every fifth state of the first 40 steps of ``policy``'s own deterministic RBF episode (reset seed 0), once apples
    have gathered, as one batch."""
    obs, states = env.reset(seed=0)[0], []
    for t in range(40):
        states += [obs] if t % 5 == 4 else []
        obs = env.step(policy.predict(obs, deterministic=True)[0])[0]
    return parse_obs(obs_as_tensor({k: np.stack([o[k] for o in states]) for k in states[0]}, th.device("cpu")))


def sent_task_profits(decision: Decision, view: ObsView) -> th.Tensor:
    """(B, M) r_j − Σ pair costs of the team task j sends, 0 where none is sent; asserts that every kept team covers
    its task and is made of the task's candidates."""
    team = (decision.pick_rank >= 0) & decision.kept.unsqueeze(-1)  # (B, M, N)
    supplied = th.einsum("bmn,bnk->bmk", team.float(), view.supply)
    assert bool((supplied >= view.demand - 1e-5).all(-1)[decision.kept].all())  # every kept team covers its task
    assert bool((team <= decision.candidates).all())  # and is made of the task's candidates
    cost = (team.float() * view.pair_cost.transpose(1, 2)).sum(-1)
    return decision.kept * (view.reward - cost)


def test_team_search_takes_each_tasks_most_profitable_team():
    """With the ``team_search`` decoder of K_s samples each task of a deterministic decision sends the best, by its
    profit, of the
    pointer's argmax team and K_s − 1 sampled ones: a team of its own candidates that covers it, never less profitable
    than the argmax's and more in some of these RBF tasks; reproducible, and sampled decisions do not search."""
    env = gym.make("TaskAlloc/RBF-v0")
    plain, searching, again = (make_policy(env, "team_search", {"samples": k}) for k in (1, 32, 32))
    view = episode_view(env, plain)
    searching.load_state_dict(plain.state_dict())
    again.load_state_dict(plain.state_dict())

    with th.no_grad():
        base, best = plain.decide(view, deterministic=True), searching.decide(view, deterministic=True)
        assert th.equal(base.candidates, best.candidates)  # the pre-assignment is the argmax's
        p0, p1 = sent_task_profits(base, view), sent_task_profits(best, view)
        assert bool((p1 >= p0 - 1e-5).all()) and bool((p1 > p0 + 1e-5).any())
        assert th.equal(again.decide(view, deterministic=True).env_action, best.env_action)
        th.manual_seed(1)
        sampled = plain.decide(view, deterministic=False).env_action
        th.manual_seed(1)
        assert th.equal(searching.decide(view, deterministic=False).env_action, sampled)
    for bad in ({"samples": 0}, {"temperature": -1.0}, {"exact": 1}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            get_decoding_strategy("team_search", **bad)


def test_exact_covers_send_each_tasks_exact_cover():
    """With the ``exact_covers`` decoder each task of a deterministic decision sends a team of its own candidates as
    profitable as the exact most profitable cover of those candidates (solved here task by task), never less than the
    team search's and more in some of these RBF tasks; the pre-assignment is the argmax's, sampled decisions do not
    search, and a non-bool value is refused."""
    from sb3_taskalloc.baselines.milp import max_profit_cover

    env = gym.make("TaskAlloc/RBF-v0")
    plain, searching, exact = (
        make_policy(env, *decoder) for decoder in (("argmax",), ("team_search", {"samples": 16}), ("exact_covers",))
    )
    view = episode_view(env, plain)
    searching.load_state_dict(plain.state_dict())
    exact.load_state_dict(plain.state_dict())
    with th.no_grad():
        found, best = searching.decide(view, deterministic=True), exact.decide(view, deterministic=True)
        assert th.equal(best.candidates, plain.decide(view, deterministic=True).candidates)

        p_search, p_exact = sent_task_profits(found, view), sent_task_profits(best, view)
        assert bool((p_exact >= p_search - 1e-5).all()) and bool((p_exact > p_search + 1e-5).any())
        supply, demand, reward, cost = (x.double().numpy() for x in (view.supply, view.demand, view.reward, view.pair_cost))
        solved = 0
        for b, j in zip(*np.nonzero(best.candidates.any(-1).numpy()), strict=True):
            ents = np.flatnonzero(best.candidates[b, j].numpy())
            _, _, res = max_profit_cover(supply[b, ents], demand[b, [j]], reward[b, [j]], cost[b][ents][:, [j]])
            optimum = max(0.0, -float(res.fun))
            assert float(p_exact[b, j]) == pytest.approx(optimum, rel=1e-4, abs=1e-4)
            solved += optimum > 0
        assert solved > 0
        th.manual_seed(1)
        sampled = plain.decide(view, deterministic=False).env_action
        th.manual_seed(1)
        assert th.equal(exact.decide(view, deterministic=False).env_action, sampled)
    with pytest.raises(ValueError, match="unknown decoding strategy 'exact'"):
        make_policy(env, "exact")


def test_exact_top_pre_assigns_by_the_exact_cover_of_the_policys_top_tasks():
    """With the ``exact_top`` decoder of k tasks each round of a deterministic decision pre-assigns by the exact most
    profitable
    cover of the pairs joining each entity to one of its k most probable tasks: with k = 1 every candidate keeps its
    argmax task, the first round is as profitable as each task's exact cover of the argmax's candidates, the
    candidates of the tasks the solver does not cover are left free for the next round, and over three rounds the
    decision is that of ``exact_covers``; with k = M the first round is
    worth the per-step MILP's optimum (solved here; 16 free robots keep it tractable). Sampled decisions do not search,
    and bad values are refused."""
    from sb3_taskalloc.baselines.milp import max_profit_cover

    env = gym.make("TaskAlloc/RBF-v0")
    M = env.observation_space["task_mask"].shape[0]
    plain, exact, top1, every, exact_rounds, top1_rounds = (
        make_policy(env, *decoder, **kw)
        for decoder, kw in (
            (("argmax",), {}),
            (("exact_covers",), {}),
            (("exact_top", {"top": 1}), {}),
            (("exact_top", {"top": M}), {}),
            (("exact_covers",), {"rounds": 3}),
            (("exact_top", {"top": 1}), {"rounds": 3}),
        )
    )
    view = episode_view(env, plain)
    # At most 16 free robots per state, so that HiGHS proves every round's cover optimal within its time limit.
    view = view._replace(entity_mask=view.entity_mask & (view.entity_mask.cumsum(-1) <= 16))
    for policy in (exact, top1, every, exact_rounds, top1_rounds):
        policy.load_state_dict(plain.state_dict())
    with th.no_grad():
        argmax, by_task = plain.decide(view, deterministic=True), exact.decide(view, deterministic=True)
        first, full = top1.decide(view, deterministic=True), every.decide(view, deterministic=True)
        assert bool((first.candidates <= argmax.candidates).all())  # k = 1: the argmax's tasks, a subset of its pairs
        assert bool((first.candidates.sum(-1) < argmax.candidates.sum(-1)).any())  # the uncovered tasks' left free
        p_task, p_top1 = sent_task_profits(by_task, view).sum(-1), sent_task_profits(first, view).sum(-1)
        th.testing.assert_close(p_top1, p_task, rtol=1e-5, atol=1e-4)  # disjoint candidate sets: one cover per task
        # Over rounds the argmax's tasks count as tried, covered or not: k = 1 decides as the exact covers do.
        assert th.equal(top1_rounds.decide(view, True).env_action, exact_rounds.decide(view, True).env_action)
        p_full = sent_task_profits(full, view).sum(-1)
        supply, demand, reward, cost = (x.double().numpy() for x in (view.supply, view.demand, view.reward, view.pair_cost))
        for b in range(p_full.shape[0]):
            free, open_ = np.flatnonzero(view.entity_mask[b].numpy()), np.flatnonzero(view.task_mask[b].numpy())
            _, _, res = max_profit_cover(supply[b, free], demand[b, open_], reward[b, open_], cost[b][np.ix_(free, open_)])
            assert float(p_full[b]) == pytest.approx(max(0.0, -float(res.fun)), rel=1e-4, abs=1e-4)
        assert bool((p_full >= p_top1 - 1e-4).all()) and bool((p_full > p_top1 + 1e-4).any())
        th.manual_seed(1)
        sampled = plain.decide(view, deterministic=False).env_action
        th.manual_seed(1)
        assert th.equal(top1.decide(view, deterministic=False).env_action, sampled)
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="top"):
            get_decoding_strategy("exact_top", top=bad)


def test_exact_searches_stop_each_solve_at_the_node_limit(monkeypatch):
    """The decision-time exact searches bound each HiGHS solve by its node limit (work, the same on any machine), with
    the time limit only as a safety net; a caller's own limits reach the solver (every row solved by HiGHS here)."""
    from sb3_taskalloc.baselines import milp
    from sb3_taskalloc.two_stage_sac import search

    solve, limits = milp.max_profit_cover, []
    monkeypatch.setattr(milp, "max_profit_cover", lambda *a, **k: limits.append(k) or solve(*a, **k))
    monkeypatch.setattr(search, "SHARED_NODE_LIMIT", 0)  # every row to HiGHS, not task by task first
    env = gym.make("TaskAlloc/RBF-v0")
    policy = make_policy(env, "exact_top", {"top": 2}, rounds=2)
    view = episode_view(env, make_policy(env))
    view = view._replace(entity_mask=view.entity_mask & (view.entity_mask.cumsum(-1) <= 16))
    with th.no_grad():
        policy.decide(view, deterministic=True)
    assert len(limits) >= view.pair_cost.shape[0]  # one solve per state and round at least
    assert all(k["node_limit"] == search.EXACT_NODE_LIMIT for k in limits)
    assert all(k["time_limit"] == search.EXACT_TIME_LIMIT for k in limits)
    limits.clear()
    search.exact_covers(view, view.valid & view.assignable.unsqueeze(-1), node_limit=3, time_limit=5.0)
    assert limits and all(k["node_limit"] == 3 and k["time_limit"] == 5.0 for k in limits)


@pytest.mark.parametrize(
    ("kwargs", "agnostic"),
    [({}, True), ({"preassign": False}, True), ({"encoder": "mlp"}, False), ({"mixer": "global"}, False)],
)
def test_size_agnostic_is_declared_by_the_components(kwargs, agnostic):
    """The policy is size-agnostic exactly when every component it was built from says so."""
    policy = make_policy(gym.make("TaskAlloc/EPT-v0"), **kwargs)
    assert policy.size_agnostic is agnostic
    modules = [m for m in (policy.actor, policy.critic, policy.selector, policy.select_critic) if m is not None]
    assert all(isinstance(m.size_agnostic, bool) for m in modules)
    assert policy.size_agnostic == all(m.size_agnostic for m in modules)


def test_heuristic_init_follows_the_cost_rules():
    """Untrained (``heuristic_init=True``), the deterministic policy sends every free entity to its cheapest open task
    and every task's pointer picks the candidate with the lowest pair cost per unit of remaining demand covered."""
    th.manual_seed(0)
    env = gym.make("TaskAlloc/RBF-v0")
    policy = make_policy(env)
    assert policy.actor is not None
    checked = 0
    for seed in range(6):
        view = parse_obs(batch([env.reset(seed=seed)[0]]))
        free = view.assignable[0]
        choice = policy.actor(view).get_actions(True)[0]
        cost = view.pair_cost[0].masked_fill(~view.valid[0], th.inf)
        th.testing.assert_close(cost[free, choice[free]], cost[free].min(-1).values)
        task_of = th.where(view.assignable, choice.unsqueeze(0), -1)
        st = SelectState(view, task_of)
        task_state, dyn = st.features()
        head = policy.selector.head
        logits = head(head.embed_entities(view), task_state, dyn, task_of).unsqueeze(1).expand_as(st.seg)
        mask = st.choice_mask()[0]
        unit = (st.pc_own / st.useful[0].clamp_min(1e-6))[0]
        for j in mask.any(-1).nonzero().flatten().tolist():
            pick = int(logits[0, j].masked_fill(~mask[j], -th.inf).argmax())
            assert unit[pick] == pytest.approx(float(unit[mask[j]].min()), rel=1e-5)
            checked += 1
    assert checked >= 3, "too few tasks had a choice to check the pointer"
    plain = make_policy(env, heuristic_init=False)
    assert (plain.selector.head.dyn.weight[0, :-1] != 0).all()  # PyTorch's default init: every feature weighed


def test_rule_weights_set_the_pre_assign_rule(tmp_path):
    """``rule_weights`` replace the rule's weights by feature name: with only the margin weighed, every free entity goes
    to the open task of its largest margin (reward − pair cost); the weights are saved with the model; an unknown
    feature or a rule without the pair term is refused by name."""
    from sb3_taskalloc import TwoStageSAC

    env = gym.make("TaskAlloc/MT-v0")
    policy = make_policy(env, rule_weights={"pair_cost": 0.0, "margin": 1.0})
    assert policy.actor is not None
    for seed in range(3):
        view = parse_obs(batch([env.reset(seed=seed)[0]]))
        free = view.assignable[0]
        choice = policy.actor(view).get_actions(True)[0]
        margin = (view.reward[0].unsqueeze(0) - view.pair_cost[0]).masked_fill(~view.valid[0], -th.inf)
        th.testing.assert_close(margin[free, choice[free]], margin[free].max(-1).values)
    with pytest.raises(ValueError, match="unknown pair features \\['distance'\\]"):
        make_policy(env, rule_weights={"distance": 1.0})
    with pytest.raises(ValueError, match="got heuristic_init=False"):
        make_policy(env, rule_weights={"margin": 1.0}, heuristic_init=False)
    for ablation in ({"encoder": "mlp"}, {"preassign": False}):  # no pair read-out: nothing to set (the table's rows)
        make_policy(env, rule_weights={"margin": 1.0}, **ablation)
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/MT-v0", device="cpu", policy_kwargs={"rule_weights": {"margin": 3.0}})
    model.save(tmp_path / "m.zip")
    loaded = TwoStageSAC.load(tmp_path / "m.zip", device="cpu")
    assert loaded.policy.rule_weights == {"margin": 3.0}
    th.testing.assert_close(loaded.policy.actor_prior.scorer.pair.weight, model.policy.actor_prior.scorer.pair.weight)


def test_heuristic_init_beats_default_init_untrained():
    """The rule-initialised policy allocates far better than PyTorch's default init before any learning (RBF)."""
    env = gym.make("TaskAlloc/RBF-v0")
    returns = {}
    for heuristic in (True, False):
        th.manual_seed(0)
        policy = make_policy(env, heuristic_init=heuristic)
        obs, _ = env.reset(seed=5)
        total = 0.0
        for _ in range(40):
            action = policy.decide(parse_obs(batch([obs])), deterministic=True).env_action[0].numpy()
            obs, reward, *_ = env.step(action)
            total += float(reward)
        returns[heuristic] = total
    assert returns[True] > returns[False] + 10.0, returns


def test_frozen_priors_skip_only_zero_dot_products():
    """The rule-initialised frozen priors skip their dot products (task embeddings identically 0) and score exactly as
    the full computation; priors with non-zero task embeddings (a loaded state, or ``heuristic_init=False``) do not."""
    th.manual_seed(0)
    env = gym.make("TaskAlloc/RBF-v0")
    policy = make_policy(env)
    assert policy.actor_prior is not None
    scorer, head = policy.actor_prior.scorer, policy.selector_prior.head
    assert scorer.skip_dot and head.skip_dot
    assert not policy.actor.scorer.skip_dot and not policy.selector.head.skip_dot  # trained copies always compute
    view = parse_obs(batch(sample_observations("TaskAlloc/RBF-v0", 8, seed=3)))
    task_of = th.where(view.assignable, policy.actor_prior(view).get_actions(True), -1)
    task_state, dyn = SelectState(view, task_of).features()
    fast = (scorer(view), head(head.embed_entities(view), task_state, dyn, task_of))
    assert head.embed_entities(view).shape[-1] == 0  # the entity MLP is not run
    scorer.skip_dot = head.skip_dot = False
    full = (scorer(view), head(head.embed_entities(view), task_state, dyn, task_of))
    for a, b in zip(fast, full, strict=True):
        th.testing.assert_close(a, b, rtol=0, atol=0)
    # A state whose priors have non-zero task embeddings turns the shortcut off when loaded.
    state = dict(policy.state_dict())
    state["actor_prior.scorer.encoder.f_g.2.bias"] = th.ones_like(state["actor_prior.scorer.encoder.f_g.2.bias"])
    state["selector_prior.head.task.2.bias"] = th.ones_like(state["selector_prior.head.task.2.bias"])
    policy.load_state_dict(state)
    assert not policy.actor_prior.scorer.skip_dot and not policy.selector_prior.head.skip_dot
    assert not make_policy(env, heuristic_init=False).selector_prior.head.skip_dot


def test_optimizers_default_to_fused_adam():
    """Adam runs fused unless ``optimizer_kwargs`` picks an implementation or another optimizer is chosen."""
    env = gym.make("TaskAlloc/Almighty-v0")
    policy = make_policy(env)
    assert policy.actor is not None and policy.critic is not None
    for module in (policy.actor, policy.critic, policy.selector, policy.select_critic):
        assert module.optimizer.defaults["fused"] is True
    chosen = make_policy(env, optimizer_kwargs={"foreach": True})
    assert chosen.selector.optimizer.defaults["foreach"] is True and not chosen.selector.optimizer.defaults["fused"]
    assert "fused" not in chosen.optimizer_kwargs  # the user's kwargs are saved unchanged
    sgd = make_policy(env, optimizer_class=th.optim.SGD)
    assert isinstance(sgd.selector.optimizer, th.optim.SGD)


@pytest.mark.parametrize("n_attention_layers", [0, 1])
def test_scorer_dot_product_equals_its_definition(n_attention_layers):
    """``TAMEncoder.dot`` (the entity MLP's last layer moved to the task side) equals h_i·g_j / scale computed from the
    embeddings, in value and in every parameter's gradient."""
    th.manual_seed(0)
    env = gym.make("TaskAlloc/RBF-v0")
    policy = make_policy(env, n_attention_layers=n_attention_layers, heuristic_init=False)
    assert policy.actor is not None
    encoder, scale = policy.actor.scorer.encoder, policy.actor.scorer.scale
    view = parse_obs(batch(sample_observations("TaskAlloc/RBF-v0", 6, seed=1)))
    weights = th.randn(view.pair_cost.shape, dtype=th.float64)

    def value_and_grads(fn):
        encoder.zero_grad()
        out = fn()
        (out.double() * weights).sum().backward()
        return out.detach(), [p.grad.clone() for p in encoder.parameters()]

    def reference():
        h, g = encoder(view)
        return h @ g.transpose(1, 2) / scale

    fast, fast_grads = value_and_grads(lambda: encoder.dot(view, scale))
    ref, ref_grads = value_and_grads(reference)
    th.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-5)
    for a, b in zip(fast_grads, ref_grads, strict=True):
        th.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


def test_narrow_linear_matches_linear():
    """``NarrowLinear`` (narrow inputs, reordered weight-gradient product) is ``nn.Linear`` in value and gradients, is
    what the MLPs use for the raw features, and keeps the state-dict keys."""
    from sb3_taskalloc.common.torch_layers import NarrowLinear, linear, mlp

    th.manual_seed(0)
    fast = NarrowLinear(8, 64)
    ref = th.nn.Linear(8, 64)
    ref.load_state_dict(fast.state_dict())
    x = th.randn(4, 300, 8)  # 1,200 rows: at least NarrowLinear.min_rows, so the reordered product is used
    assert NarrowLinear.min_rows <= 1200 and "NarrowInputLinear" in type(fast(x).grad_fn).__name__
    assert "NarrowInputLinear" not in type(fast(x[:1, :10]).grad_fn).__name__  # few rows: the plain layer
    grads = []
    for layer in (fast, ref):
        xi = x.clone().requires_grad_(True)
        (layer(xi) ** 2).sum().backward()
        grads.append((layer(x), xi.grad, layer.weight.grad, layer.bias.grad))
    for a, b in zip(*grads, strict=True):
        th.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    with th.no_grad():
        th.testing.assert_close(fast(x), ref(x))
    assert isinstance(mlp(8, 64, 64)[0], NarrowLinear) and type(mlp(64, 64, 64)[0]) is th.nn.Linear
    assert type(linear(7, 1)) is th.nn.Linear  # one output: nothing to gain
    assert list(fast.state_dict()) == ["weight", "bias"]


@pytest.mark.parametrize("state_value", [False, True])
def test_pointer_scores_equal_their_definition(state_value):
    """``PointerHead`` (one batched product over all tasks, then each entity's own column) scores
    u_i = d_i·e_j^t / √d + w·x_i^t (+ b(e_j^t)) with d = entity MLP, e = task MLP, s_j^t the task state, x_i^t the
    basis, as defined, in value and in every parameter's gradient."""
    from sb3_taskalloc.common.torch_layers import SELECT_DYN, PointerHead

    th.manual_seed(0)
    view = parse_obs(batch(sample_observations("TaskAlloc/RBF-v0", 5, seed=2)))
    head = PointerHead(view.entity.shape[-1], view.supply.shape[-1], 16, state_value=state_value)
    task_of = th.where(view.assignable, th.randint(0, view.task_mask.shape[1], view.entity_mask.shape), -1)
    st = SelectState(view, task_of)
    task_state, dyn = select_features(
        view,
        task_of,
        st.pc_own,
        st.rem.expand(3, -1, -1, -1),
        st.cost.expand(3, -1, -1),
        st.npick.expand(3, -1, -1),
    )
    weights = th.randn(3, *task_of.shape, dtype=th.float64)
    own = task_of.clamp_min(0)
    assert dyn.shape[-1] == head.dyn.in_features == SELECT_DYN

    def reference():
        d, e = head.entity(view.entity), head.task(task_state)  # (B, N, H), (T, B, M, H)
        e_own = th.stack([e[:, b, own[b]] for b in range(own.shape[0])], 1)  # (T, B, N, H)
        scores = (e_own * d).sum(-1) / head.scale + head.dyn(dyn).squeeze(-1)
        if head.value is not None:
            scores = scores + th.gather(head.value(e).squeeze(-1), -1, own.expand(3, -1, -1))
        return scores

    results = []
    for fn in (lambda: head(head.embed_entities(view), task_state, dyn, task_of), reference):
        head.zero_grad()
        out = fn()
        (out.double() * weights).sum().backward()
        results.append((out.detach(), [p.grad.clone() for p in head.parameters() if p.grad is not None]))
    (fast, fast_grads), (ref, ref_grads) = results
    assert fast.shape == (3, *task_of.shape)
    th.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-5)
    assert len(fast_grads) == len(ref_grads) == len(list(head.parameters()))
    for a, b in zip(fast_grads, ref_grads, strict=True):
        th.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    # Three consecutive copies of each row share its entity embeddings: the scores of the embeddings repeated.
    with th.no_grad():
        d, copied = head.embed_entities(view), (task_state.repeat_interleave(3, 1), dyn.repeat_interleave(3, 1))
        shared = head(d, *copied, task_of.repeat_interleave(3, 0))
        th.testing.assert_close(shared, head(d.repeat_interleave(3, 0), *copied, task_of.repeat_interleave(3, 0)))
        th.testing.assert_close(shared[:, ::3], fast)


def test_a_decode_drops_finished_rows_alike(monkeypatch):
    """``decode_round`` decodes on without the rows whose tasks are all done (``SelectState.take``/``put``) and scores
    the copies of a round with their rows' entity embeddings shared: the same pick orders, costs and kept teams as the
    fixed-length loop over every row, for the argmax and for samples from one seeded stream, on 6 copies of 6 RBF
    states whose rows finish at different steps."""
    from sb3_taskalloc.two_stage_sac.select_stage import decode_round

    env = gym.make("TaskAlloc/RBF-v0")
    th.manual_seed(0)
    policy = make_policy(env)
    one = parse_obs(batch(sample_observations("TaskAlloc/RBF-v0", 6, seed=1)))
    rounds: list = []
    with th.no_grad():
        policy.decide(one, deterministic=True, rounds_out=rounds)
        head, (_, task_of) = policy.selector.head, rounds[0]
        view, copies = ObsView(*(x.repeat_interleave(6, 0) for x in one)), task_of.repeat_interleave(6, 0)
        taken: list[int] = []
        take = SelectState.take
        monkeypatch.setattr(SelectState, "take", lambda st, rows: taken.append(len(rows)) or take(st, rows))
        for deterministic in (True, False):
            taken.clear()
            fixed = decode_round(head, view, copies, deterministic, generator=th.Generator().manual_seed(0), fixed_picks=True)
            assert not taken
            for embedded in (None, head.embed_entities(one)):
                st = decode_round(
                    head, view, copies, deterministic, generator=th.Generator().manual_seed(0), embedded=embedded
                )
                assert th.equal(st.rank, fixed.rank) and th.equal(st.cost, fixed.cost) and th.equal(st.kept(), fixed.kept())
            assert taken and min(taken) < len(copies) // 2  # rows were dropped, more than once


def test_logit_scale_multiplies_the_pre_assign_logits():
    """``logit_scale`` κ: the pre-assign logits are κ times the scores, the argmax is unchanged, sampling is sharper;
    a non-positive κ is refused. The default is κ = 100 (κ_s = 10) for the rule-initialised actors, 1 for a random start
    (the paper's, and the W/o TAM actor, which has no rule)."""
    env = gym.make("TaskAlloc/RBF-v0")
    view = parse_obs(batch(sample_observations("TaskAlloc/RBF-v0", 4)))
    ruled, paper, flat = make_policy(env), make_policy(env, heuristic_init=False), make_policy(env, encoder="mlp")
    assert (ruled.logit_scale, ruled.select_logit_scale) == (100.0, 10.0)
    assert (paper.logit_scale, paper.select_logit_scale) == (1.0, 1.0)
    assert (flat.logit_scale, flat.select_logit_scale) == (1.0, 10.0)  # its pointer starts at the unit-cost rule
    th.manual_seed(0)
    plain = make_policy(env, logit_scale=1.0)
    th.manual_seed(0)
    sharp = make_policy(env, logit_scale=50.0)
    assert plain.actor is not None and sharp.actor is not None
    d1, d50 = plain.actor(view), sharp.actor(view)
    free = view.assignable
    th.testing.assert_close(
        d50.logits[free].masked_fill(~view.valid[free], 0), 50 * d1.logits[free].masked_fill(~view.valid[free], 0)
    )
    assert th.equal(d1.get_actions(True)[free], d50.get_actions(True)[free])
    assert d50.entropy()[free].mean() < d1.entropy()[free].mean()
    for bad in (0.0, -1.0, float("inf")):
        with pytest.raises(ValueError, match="logit_scale"):
            make_policy(env, logit_scale=bad)


@pytest.mark.parametrize("env_id", ["TaskAlloc/RBF-v0", "TaskAlloc/MT-v0"])
def test_a_fixed_length_decode_picks_alike_and_traces_whole(env_id):
    """``decode_round(fixed_picks=True)`` runs all N pick steps with no host check in between: the same pick orders,
    costs and kept teams as the loop that stops once no task is active (argmax, and samples from a seeded global
    stream over 8 copies of the round); on MT the tracer of ``torch.compile(fullgraph=True)``
    (``torch._dynamo.explain``) finds one graph and no break in 4 of its pick steps (the tracer unrolls the loop, whose
    steps run the same code: all of MT's took 13–23 s to trace, RBF's twice that)."""
    import torch._dynamo

    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.two_stage_sac.select_stage import decode_round

    policy = TwoStageSAC.from_zoo(env_id, seed=0, n_envs=1).policy
    obs, _ = gym.make(env_id).reset(seed=3)
    rounds: list = []
    with th.no_grad():
        policy.decide(policy.parse(policy.obs_to_tensor(obs)[0]), deterministic=True, rounds_out=rounds)
        one, task_of = rounds[0]
        view = ObsView(*(x.repeat_interleave(8, 0) for x in one))
        task_of = task_of.repeat_interleave(8, 0)
        head = policy.selector.head
        for deterministic in (True, False):
            th.manual_seed(0)
            stops = decode_round(head, view, task_of, deterministic, temperature=2.0)
            th.manual_seed(0)
            fixed = decode_round(head, view, task_of, deterministic, temperature=2.0, fixed_picks=True)
            assert th.equal(stops.rank, fixed.rank) and th.equal(stops.cost, fixed.cost)
            assert th.equal(stops.kept(), fixed.kept())
            assert 0 <= int(stops.rank.max()) < task_of.shape[1] - 1  # picks were made, and the fixed loop ran on
        assert (stops.rank != stops.rank[:1]).any()  # the sampled copies differ

        def decode(v: ObsView, t: th.Tensor) -> th.Tensor:
            return decode_round(head, v, t, False, fixed_picks=True, steps=4).rank

        if env_id == "TaskAlloc/MT-v0":
            explained = torch._dynamo.explain(decode)(view, task_of)
            assert explained.graph_count == 1 and explained.graph_break_count == 0, explained.break_reasons


@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_decisions_are_the_cpus():
    """A deterministic decision of the zoo's RBF policy on CUDA is the CPU's, for a batch of states."""
    from sb3_taskalloc import TwoStageSAC

    policy = TwoStageSAC.from_zoo("TaskAlloc/RBF-v0", seed=0, n_envs=1, device="cpu").policy
    obs = batch(sample_observations("TaskAlloc/RBF-v0", 6, seed=2))
    with th.no_grad():
        on_cpu = policy.decide(policy.parse(policy.obs_to_tensor(obs)[0]), deterministic=True).env_action
        policy.to("cuda")
        on_cuda = policy.decide(policy.parse(policy.obs_to_tensor(obs)[0]), deterministic=True).env_action
    assert on_cuda.is_cuda and th.equal(on_cuda.cpu(), on_cpu)
