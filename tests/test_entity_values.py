"""The learned per-entity value in the exact pre-assignment (``entity_value``, implementation detail 27)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from sb3_taskalloc import TwoStageSAC
from sb3_taskalloc.two_stage_sac import EntityValueDecoder, fit_entity_values
from sb3_taskalloc.two_stage_sac.decoding import decide_preassigned, get_decoding_strategy
from sb3_taskalloc.two_stage_sac.entity_values import CONTROLS, mean_distance, pair_values, post_decision, regress
from tests.test_decoding import _check_best_assignments

SMALL = {"entity_rows": range(12)}  # twelve robots keep an RBF episode short
#: e per coordinate on RBF's 7 × 7 grid: the mean |x − u| over the cells u, computed here by hand
E_AXIS = np.abs(np.arange(7)[:, None] - np.arange(7)[None, :]).mean(1)


@pytest.fixture(scope="module")
def rbf_model() -> TwoStageSAC:
    return TwoStageSAC("TAMPolicy", gym.make("TaskAlloc/RBF-v0", **SMALL), policy_kwargs={"hidden_dim": 16}, seed=0)


def _states(model: TwoStageSAC, steps: int = 12, seed: int = 3):
    """(obs, env) pairs of ``steps`` argmax steps of the small RBF env, each env a copy at its state."""
    import copy

    env = gym.make("TaskAlloc/RBF-v0", **SMALL)
    obs, _ = env.reset(seed=seed)
    states = []
    for _ in range(steps):
        states.append((obs, copy.deepcopy(env.unwrapped)))
        obs = env.step(model.predict(obs, deterministic=True)[0])[0]
    return states


def _view(model: TwoStageSAC, obs):
    return model.policy.parse(model.policy.obs_to_tensor(obs)[0])


def test_pair_values_from_the_observation_match_the_env(rbf_model):
    """v_ij = θ_free − θ_τ·(d_ij + 1) + θ_e·(e(cell_i) − e(cell_j)), with the env's own distances and cells."""
    theta = (-0.11, -0.034, 0.025)
    for obs, env in _states(rbf_model, steps=8):
        v = pair_values(_view(rbf_model, obs), theta, 7)[0].double().numpy()
        here = env._pos.astype(int)
        e_here = E_AXIS[here[:, 0]] + E_AXIS[here[:, 1]]
        e_there = E_AXIS[env._tpos[:, 0].astype(int)] + E_AXIS[env._tpos[:, 1].astype(int)]
        expected = theta[0] - theta[1] * (env._dist + 1.0) + theta[2] * (e_here[:, None] - e_there[None, :])
        np.testing.assert_allclose(v, expected, atol=1e-6)
    assert float(mean_distance(th.tensor([3.0, 3.0]), 7)) == pytest.approx(2 * 12 / 7)  # the centre: 12/7 per axis


def test_zero_values_decide_as_exact_top_and_the_objective_is_the_best_assignment(rbf_model):
    """θ = 0 is ``exact_top`` of the same ``top``; with θ ≠ 0 and every pair allowed, each state's decision is worth,
    at the costs c + v, the best of all assignments enumerated."""
    policy = rbf_model.policy
    obs = [o for o, _ in _states(rbf_model, steps=10)]
    view = policy.parse(policy.obs_to_tensor({k: np.stack([o[k] for o in obs]) for k in obs[0]})[0])
    view = view._replace(entity_mask=view.entity_mask & (view.entity_mask.cumsum(-1) <= 4))  # (M + 1)^4 assignments
    M, theta = view.reward.shape[1], (0.3, -0.2, 0.1)
    with th.no_grad():
        zero = decide_preassigned(policy, view, EntityValueDecoder(top=2))
        exact = decide_preassigned(policy, view, get_decoding_strategy("exact_top", top=2))
        valued = decide_preassigned(policy, view, EntityValueDecoder(top=M, theta=theta))
    assert th.equal(zero.env_action, exact.env_action)
    assert _check_best_assignments(view, valued, view.pair_cost + pair_values(view, theta, 7)) >= 3


def test_post_decision_features_count_free_busy_and_cells(rbf_model):
    """Σ φ after a decision, from the observation and the tracked targets, equals the env's state after it."""
    env = gym.make("TaskAlloc/RBF-v0", **SMALL)
    obs, _ = env.reset(seed=4)
    u = env.unwrapped
    target = np.zeros((u.max_entities, 2))
    for _ in range(15):
        action = rbf_model.predict(obs, deterministic=False)[0]
        phi = post_decision(_view(rbf_model, obs), np.asarray(action), target, 7)
        sent = (action < u.max_tasks) & u._free
        task = np.where(sent, action, u._assigned)
        busy = task >= 0
        tau = np.where(busy, u._dist[np.arange(len(task)), np.maximum(task, 0)] + 1.0, 0.0)
        cell = np.where(busy[:, None], u._tpos[np.maximum(task, 0)], u._pos).astype(int)
        expected = [(~busy).sum(), tau.sum(), (E_AXIS[cell[:, 0]] + E_AXIS[cell[:, 1]]).sum()]
        np.testing.assert_allclose(phi, expected, atol=1e-9)
        obs = env.step(action)[0]


def test_regression_recovers_the_values_under_time_controls():
    rng = np.random.default_rng(0)
    n = 400
    phi = rng.normal(size=(n, 3)) * [5.0, 20.0, 30.0] + [10.0, 40.0, 100.0]
    t = rng.uniform(0, 1, n)
    rows = np.column_stack([phi, np.ones(n), t, t**2])
    y = phi @ [0.5, -0.1, 0.02] + 80 * (1 - t) ** 2 + rng.normal(scale=0.01, size=n)
    theta, r2 = regress(rows, y, ridge=1e-9)
    np.testing.assert_allclose(theta, [0.5, -0.1, 0.02], atol=2e-3)
    assert r2 > 0.999 and rows.shape[1] - CONTROLS == 3


def test_fit_runs_the_decoder_in_the_loop_and_damps(rbf_model):
    short = {**SMALL, "max_episode_steps": 15}
    fit = fit_entity_values(rbf_model, "TaskAlloc/RBF-v0", iterations=2, episodes=1, env_kwargs=short)
    assert fit.thetas[0] == (0.0, 0.0, 0.0) and len(fit.thetas) == 3 and len(fit.r2) == 2
    assert all(np.isfinite(theta).all() for theta in fit.thetas) and fit.thetas[1] != fit.thetas[0]
    assert fit.decoder.theta == fit.thetas[-1] and fit.decoder.config["top"] == 2
    assert get_decoding_strategy("entity_value", theta=fit.thetas[-1]).theta == fit.decoder.theta
    with pytest.raises(ValueError, match="Manhattan"):
        fit_entity_values(rbf_model, "TaskAlloc/MT-v0")
    with pytest.raises(ValueError, match="damping"):
        fit_entity_values(rbf_model, "TaskAlloc/RBF-v0", damping=1.5)
    with pytest.raises(ValueError, match="theta must be three finite numbers"):
        EntityValueDecoder(theta=(1.0, float("nan"), 0.0))


def test_fit_interrupted_keeps_the_iterations_done(rbf_model, monkeypatch):
    """Ctrl-C during the second iteration returns the first iteration's θ with a warning; during the first it raises."""
    from sb3_taskalloc.two_stage_sac import entity_values

    short = {**SMALL, "max_episode_steps": 15}
    real_play, calls = entity_values.play, []

    def play_until(stop: int):
        def play(*args, **kwargs):
            calls.append(1)
            if len(calls) == stop:
                raise KeyboardInterrupt
            return real_play(*args, **kwargs)

        return play

    monkeypatch.setattr(entity_values, "play", play_until(2))
    with pytest.warns(UserWarning, match="interrupted after 1 of 2 iterations"):
        fit = fit_entity_values(rbf_model, "TaskAlloc/RBF-v0", iterations=2, episodes=1, env_kwargs=short)
    assert len(fit.thetas) == 2 and len(fit.r2) == len(fit.train_returns) == 1
    assert fit.thetas[1] != fit.thetas[0] and fit.decoder.theta == fit.thetas[1]
    calls.clear()
    monkeypatch.setattr(entity_values, "play", play_until(1))
    with pytest.raises(KeyboardInterrupt):
        fit_entity_values(rbf_model, "TaskAlloc/RBF-v0", iterations=2, episodes=1, env_kwargs=short)


def test_distill_select_teacher_costs(rbf_model: TwoStageSAC):
    """``distill_select(teacher=...)``: the covers are solved and kept under the teacher's ``costed`` view. On RBF
    ``"recommended"`` is ``entity_value``'s costs; a surcharge under which no team pays labels nothing and leaves the
    pointer as it was; ``exact_top`` without a surcharge is the observation's costs, the same DAgger as no teacher."""
    from sb3_taskalloc.two_stage_sac.dagger import teacher_costs
    from sb3_taskalloc.two_stage_sac.decoding import recommended_decoder

    view = _view(rbf_model, _states(rbf_model, steps=1)[0][0])
    valued = teacher_costs("recommended", "TaskAlloc/RBF-v0")(view).pair_cost
    th.testing.assert_close(valued, recommended_decoder("TaskAlloc/RBF-v0").costed(view).pair_cost)
    assert not th.equal(valued, view.pair_cost)
    assert teacher_costs(None, None) is None  # the pointer's own costs (TAMPolicy.select_view)
    env_id = "TaskAlloc/Almighty-v0"

    def new_model() -> TwoStageSAC:
        return TwoStageSAC("TAMPolicy", env_id, seed=0, device="cpu", policy_kwargs={"hidden_dim": 16})

    dagger = {"iterations": 1, "episodes": 6, "epochs": 2, "seed": 0}
    plain = new_model().distill_select(env_id, **dagger)
    assert plain[0]["labelled_tasks"] > 0
    assert new_model().distill_select(env_id, teacher=get_decoding_strategy("exact_top"), **dagger) == plain
    model = new_model()
    pointer = {k: v.clone() for k, v in model.policy.selector.state_dict().items()}
    (priced_out,) = model.distill_select(env_id, teacher=get_decoding_strategy("exact_top", surcharge=1e6), **dagger)
    assert priced_out["labelled_tasks"] == 0
    assert all(th.equal(v, pointer[k]) for k, v in model.policy.selector.state_dict().items())
    with pytest.raises(ValueError, match="no decoder was measured"):
        model.distill_select(env_id, teacher="recommended", **dagger)
    for bad in ("entity_value", get_decoding_strategy("sampled")):
        with pytest.raises(ValueError, match="teacher"):
            model.distill_select(env_id, teacher=bad, **dagger)


def test_select_values_put_the_values_in_the_pointers_costs(tmp_path):
    """``TAMPolicy(select_values=...)``: the pointer's view carries c_ij + v_ij (entity_value's costs with σ = 0), its
    argmax teams are the decode on that view, which differs from the decode on the observation's costs (on the full
    RBF env: with twelve robots the teams hardly compete), and a saved model keeps the values."""
    from sb3_taskalloc.two_stage_sac.select_stage import decode_round

    theta = (-0.114, -0.041, 0.010)
    env = gym.make("TaskAlloc/RBF-v0")
    valued = TwoStageSAC("TAMPolicy", env, seed=0, policy_kwargs={"hidden_dim": 16, "select_values": {"theta": theta}})
    plain = TwoStageSAC("TAMPolicy", env, seed=0, policy_kwargs={"hidden_dim": 16})
    obs, _ = env.reset(seed=3)
    differs = 0
    for _ in range(4):
        view = _view(valued, obs)
        costed = valued.policy.select_view(view)
        th.testing.assert_close(costed.pair_cost, EntityValueDecoder(theta=theta).costed(view).pair_cost)
        assert plain.policy.select_view(view) is view  # no values: the observation's own costs
        rounds: list = []
        with th.inference_mode():
            decision = valued.policy.decide(view, deterministic=True, rounds_out=rounds)
            first = decode_round(valued.policy.selector.head, costed, rounds[0][1], deterministic=True)
            observed = decode_round(valued.policy.selector.head, view, rounds[0][1], deterministic=True)
        assert th.equal(decision.pick_rank, first.rank) and th.equal(decision.kept, first.kept())
        differs += not th.equal(observed.rank, first.rank)
        obs = env.step(decision.env_action[0].numpy())[0]
    assert differs > 0
    valued.save(tmp_path / "valued.zip")
    loaded = TwoStageSAC.load(tmp_path / "valued.zip")
    assert loaded.policy.select_values == valued.policy.select_values
    for bad in ({"theta": (1.0, 2.0)}, {"theta": (1.0, float("nan"), 0.0)}, {"theta": theta, "grid": 7}, [1.0, 2.0, 3.0]):
        with pytest.raises(ValueError, match="select_values"):
            TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", policy_kwargs={"select_values": bad})


def test_select_values_surcharge_is_exact_tops_costs(tmp_path):
    """``select_values={"surcharge": σ}`` puts ``exact_top``'s uniform surcharge in the pointer's costs, (1 + σ)·c_ij (MT's
    recommended decoder), alone or with θ on top, as ``entity_value`` with the same σ and θ; a saved model keeps it."""
    from sb3_taskalloc.two_stage_sac.decoding import ExactTopDecoder
    from sb3_taskalloc.two_stage_sac.entity_values import SelectValues

    env = gym.make("TaskAlloc/MT-v0")
    model = TwoStageSAC("TAMPolicy", env, seed=0, policy_kwargs={"hidden_dim": 16, "select_values": {"surcharge": 0.64}})
    obs, _ = env.reset(seed=1)
    view = _view(model, obs)
    costed = model.policy.select_view(view)
    th.testing.assert_close(costed.pair_cost, ExactTopDecoder(top=10, surcharge=0.64).costed(view).pair_cost)
    assert bool((costed.pair_cost[view.valid] > view.pair_cost[view.valid]).all())
    both = SelectValues.of({"theta": (0.1, 0.2, 0.3), "surcharge": 0.5})
    assert both is not None and SelectValues.of(both.config) == both
    rbf = gym.make("TaskAlloc/RBF-v0")
    rbf_view = _view(TwoStageSAC("TAMPolicy", rbf, seed=0, policy_kwargs={"hidden_dim": 16}), rbf.reset(seed=2)[0])
    expected = EntityValueDecoder(theta=(0.1, 0.2, 0.3), surcharge=0.5).costed(rbf_view).pair_cost
    th.testing.assert_close(both.costed(rbf_view).pair_cost, expected)
    model.save(tmp_path / "surcharged.zip")
    assert TwoStageSAC.load(tmp_path / "surcharged.zip").policy.select_values == SelectValues(surcharge=0.64)
    for bad in ({"surcharge": -0.1}, {"surcharge": float("nan")}, {"grid_size": 7}, {"surcharge": True}):
        with pytest.raises(ValueError, match="select_values"):
            TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", policy_kwargs={"select_values": bad})


def test_select_values_reach_training_and_dagger(monkeypatch):
    """Values that price every pair out (θ_free = 10⁶) keep no team at decision time, label nothing in DAgger and
    reach the select stage's SAC losses, which train on the pointer's own costs."""
    import sb3_taskalloc.two_stage_sac.losses as losses

    env_id = "TaskAlloc/Almighty-v0"

    def new_model(select_values: dict | None) -> TwoStageSAC:
        kwargs = {"hidden_dim": 16, "select_values": select_values}
        return TwoStageSAC("TAMPolicy", env_id, seed=0, learning_starts=8, batch_size=8, policy_kwargs=kwargs)

    priced_out = new_model({"theta": (1e6, 0.0, 0.0)})
    obs, _ = gym.make(env_id).reset(seed=0)
    M = obs["task_mask"].shape[0]
    assert (priced_out.predict(obs, deterministic=True)[0] == M).all()
    assert (new_model(None).predict(obs, deterministic=True)[0] < M).any()
    dagger = {"iterations": 1, "episodes": 4, "epochs": 1, "seed": 0}
    assert priced_out.distill_select(env_id, **dagger)[0]["labelled_tasks"] == 0
    assert new_model(None).distill_select(env_id, **dagger)[0]["labelled_tasks"] > 0
    seen: list[float] = []
    select_losses = losses.select_losses

    def spy(selector, critic, critic_target, view, *args, **kwargs):
        seen.append(float(view.pair_cost[view.valid].min()))
        return select_losses(selector, critic, critic_target, view, *args, **kwargs)

    monkeypatch.setattr(losses, "select_losses", spy)
    new_model({"theta": (1e6, 0.0, 0.0)}).learn(12)
    assert seen and min(seen) >= 1e6
