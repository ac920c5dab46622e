"""How TAMPolicy decides: rounds for the left-over entities, the pre-assignment and team searches, exact covers and the
exact pre-assignment at decision time, their node limit, and decodes of fixed length (the decoders by name:
``test_decoding.py``)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.utils import obs_as_tensor

from sb3_taskalloc import TAMPolicy
from sb3_taskalloc.common.torch_layers import ObsView, parse_obs
from sb3_taskalloc.two_stage_sac.decoding import get_decoding_strategy
from sb3_taskalloc.two_stage_sac.select_stage import Decision, SelectState
from tests.test_policies import batch, make_policy, sample_observations


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


def test_the_pooled_decoder_decides_as_w_o_pre_with_the_models_pointer():
    """``pooled`` lets a pre-assigning model's pointer decide without its pre-assignment: the tasks pick in slot order
    from one pool of free entities, as the "W/o Pre (sequence)" policy with the same pointer weights does, on RBF states
    with robots spread over many apples; it has no pre-assign rounds to record, and says so."""
    env = gym.make("TaskAlloc/RBF-v0")
    th.manual_seed(0)
    two_stage = make_policy(env, decoder="pooled")
    without = make_policy(env, preassign=False)
    without.selector.load_state_dict(two_stage.selector.state_dict())
    view = parse_obs(batch(sample_observations("TaskAlloc/RBF-v0", 6, seed=3)))
    decision = two_stage.decide(view, deterministic=True)
    pooled = decision.env_action
    assert th.equal(pooled, without.decide(view, deterministic=True).env_action)
    assert (decision.candidates.sum(1) > 1).any()  # one pool: a robot no task kept is offered to the next
    two_stage.decoder = get_decoding_strategy("argmax")
    assert not th.equal(pooled, two_stage.decide(view, deterministic=True).env_action)  # the pre-assignment decides otherwise
    two_stage.decoder = get_decoding_strategy("pooled")
    with pytest.raises(ValueError, match="'pooled' decoder has no pre-assign rounds"):
        two_stage.decide(view, deterministic=True, rounds_out=[])
    sampled = two_stage.decide(view, deterministic=False).candidates  # training's decisions stay the two stages'
    assert (sampled.sum(1) <= 1).all()  # each robot a candidate of one task


def test_the_pooled_decoders_theta_costs_the_pointer_as_select_values_do():
    """``pooled(theta=θ)`` prices the pointer's pairs with θ's per-robot values at decision time, in place of the
    model's own: a model trained without values and one trained with another θ both decide as the W/o Pre policy
    whose pointer carries θ in ``select_values``, and otherwise than ``pooled`` on their own costs; a θ that is not
    three finite numbers is refused by name."""
    env = gym.make("TaskAlloc/RBF-v0")
    th.manual_seed(0)
    theta = (-0.114, -0.041, 0.010)
    without = make_policy(env, preassign=False, select_values={"theta": theta, "grid_size": 7})
    view = parse_obs(batch(sample_observations("TaskAlloc/RBF-v0", 8, seed=5)))
    expected = without.decide(view, deterministic=True).env_action
    for own in (None, {"theta": (0.3, 0.05, -0.2), "grid_size": 7}):
        two_stage = make_policy(env, decoder="pooled", decoder_kwargs={"theta": theta}, select_values=own)
        two_stage.selector.load_state_dict(without.selector.state_dict())
        assert th.equal(two_stage.decide(view, deterministic=True).env_action, expected)
        two_stage.decoder = get_decoding_strategy("pooled")
        assert not th.equal(two_stage.decide(view, deterministic=True).env_action, expected)
    with pytest.raises(ValueError, match="theta must be three finite numbers"):
        get_decoding_strategy("pooled", theta=(0.1, float("nan"), 0.0))


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
