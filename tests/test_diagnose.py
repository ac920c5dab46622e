"""The diagnosis of the stage-1 critic: calibration against branched returns, the ranking of decision pairs, drift and
the classification of each open task, by function and by command."""

from __future__ import annotations

import copy

import gymnasium as gym
import numpy as np
import pytest


def test_diagnose_measures_calibration_and_drift(tmp_path, short_episodes):
    """The diagnosis of a model reads its critic against Monte-Carlo returns and its actor against the initial rule:
    untrained, the actor equals its rule (KL 0, no argmax changed); moved away from it, both figures see the drift."""
    import torch as th

    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.experiments.diagnose import diagnose, write

    model = TwoStageSAC("TAMPolicy", "TaskAlloc/EPT-v0", seed=0, device="cpu", policy_kwargs={"hidden_dim": 16})
    fresh = diagnose(model, "TaskAlloc/EPT-v0", episodes=1)
    assert fresh.kl_per_entity == 0 and fresh.argmax_changed == 0
    assert fresh.deterministic_return > 0 and fresh.entropy_bonus_mean > 0 and fresh.abs_reward_mean > 0
    assert -1 <= fresh.q_corr <= 1 and np.isfinite(fresh.q_scale)
    with th.no_grad():
        for p in model.policy.actor.parameters():
            p.add_(th.randn_like(p))
    moved = diagnose(model, "TaskAlloc/EPT-v0", episodes=1)
    assert moved.kl_per_entity > 1e-3 and moved.argmax_changed > 0
    # Untrained, both stages are their rules; with only the actor moved, resetting either stage isolates it.
    assert fresh.actor_only_return == fresh.pointer_only_return == fresh.deterministic_return
    assert moved.actor_only_return == moved.deterministic_return != moved.pointer_only_return
    assert moved.pointer_only_return == fresh.deterministic_return
    assert diagnose(model, "TaskAlloc/EPT-v0", episodes=1).deterministic_return == moved.deterministic_return  # restored
    path = write(moved, tmp_path)
    assert "corr(Q, G)" in path.read_text() and path.with_suffix(".json").exists()
    no_pre = TwoStageSAC(
        "TAMPolicy", "TaskAlloc/EPT-v0", seed=0, device="cpu", policy_kwargs={"preassign": False, "hidden_dim": 16}
    )
    assert np.isnan(diagnose(no_pre, "TaskAlloc/EPT-v0", episodes=1).q_corr)  # no stage-1 critic to read
    shares = [fresh.tasks_kept, fresh.tasks_short, fresh.tasks_unprofitable, fresh.tasks_no_candidates]
    assert sum(shares) == pytest.approx(1.0) and fresh.tasks_kept > 0 and "kept / short of demand" in path.read_text()


def test_calibration_figures_separate_the_critic_from_the_noise():
    """Returns G = μ + ε with Var μ = 1 and Var ε = 1 over K = 4 branches: the ceiling of corr(Q, G) is sqrt(1/2); a
    critic Q = μ correlates with the branch means Ḡ by sqrt(1 / (1 + 1/4)) and has scale Q/Ḡ = 1 / (1 + 1/4)."""
    from sb3_taskalloc.experiments.calibration import calibration_figures

    rng = np.random.default_rng(0)
    mu = rng.normal(size=20_000)
    returns = mu[:, None] + rng.normal(size=(20_000, 4))
    free = 10 + 3 * mu + rng.normal(size=20_000)
    got = calibration_figures(mu, returns, free)
    assert got["branch_states"] == 20_000
    assert got["return_ceiling"] == pytest.approx(np.sqrt(0.5), abs=0.01)
    assert got["q_corr_expected"] == pytest.approx(np.sqrt(1 / 1.25), abs=0.01)
    assert got["q_scale_expected"] == pytest.approx(1 / 1.25, abs=0.02)
    assert got["free_corr_q"] == pytest.approx(3 / np.sqrt(10), abs=0.01)
    noiseless = calibration_figures(mu, np.repeat(mu[:, None], 3, 1), free)
    assert noiseless["return_ceiling"] == pytest.approx(1.0) and noiseless["q_corr_expected"] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="K >= 2"):
        calibration_figures(mu, returns[:, :1], free)


def test_advantage_figures_separate_the_critic_from_the_noise():
    """Paired differences d_k = Δμ + ε_k with Var Δμ = 1 and Var ε = 4 over K = 4 branches: the pair means have variance
    2, so a critic ΔQ = Δμ correlates with them by sqrt(1/2), the ceiling, and agrees in sign with probability
    1/2 + arcsin(sqrt(1/2))/π = 3/4 (bivariate normal); a critic blind to the decisions reaches neither."""
    from sb3_taskalloc.experiments.calibration import advantage_figures

    rng = np.random.default_rng(0)
    delta = rng.normal(size=40_000)
    differences = delta[:, None] + 2 * rng.normal(size=(40_000, 4))
    got = advantage_figures(delta, differences)
    assert got["advantage_pairs"] == 40_000
    assert got["advantage_ceiling"] == pytest.approx(np.sqrt(0.5), abs=0.01)
    assert got["advantage_corr"] == pytest.approx(np.sqrt(0.5), abs=0.01)
    assert got["advantage_sign"] == pytest.approx(0.75, abs=0.01)
    blind = advantage_figures(rng.normal(size=40_000), differences)
    assert abs(blind["advantage_corr"]) < 0.02 and blind["advantage_sign"] == pytest.approx(0.5, abs=0.01)
    with pytest.raises(ValueError, match="K >= 2"):
        advantage_figures(delta, differences[:, :1])
    # Pairs whose every branch returned the same (the same teams sent, nothing after differed) have no order: they are
    # counted apart, not as disagreements, whatever ΔQ says of them.
    tied = np.vstack([differences[:100], np.zeros((300, 4))])
    some = advantage_figures(np.concatenate([delta[:100], rng.normal(size=300)]), tied)
    alone = advantage_figures(delta[:100], tied[:100])
    assert some["advantage_ties"] == 300 and alone["advantage_ties"] == 0
    assert some["advantage_sign"] == alone["advantage_sign"] > 0.6
    assert np.isnan(advantage_figures(delta[:3], np.zeros((3, 4)))["advantage_sign"])


def test_branch_calibration_branches_the_env_randomness(monkeypatch):
    """Copies of a state draw their own arrivals (seeded per copy, so they are reproducible), and the calibration
    branches every ``stride``-th state of each episode. On 60-step episodes, with γ = 0.7 (branches of 13 steps, where
    γ = 0.9 sums 44): the same states branched, in about half the time."""
    import torch as th

    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.experiments.calibration import _branch_returns, branch_calibration

    monkeypatch.setattr(gym.spec("TaskAlloc/RBF-v0"), "max_episode_steps", 60)
    short = {"seed": 0, "device": "cpu", "gamma": 0.7}
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", **short, policy_kwargs={"hidden_dim": 16})
    env = gym.make("TaskAlloc/RBF-v0")
    obs, _ = env.reset(seed=3)
    action = model.predict(obs, deterministic=True)[0]
    untouched = copy.deepcopy(env)
    runs = []
    for _ in range(2):
        th.manual_seed(0)
        with th.no_grad():
            runs.append(_branch_returns(model, env, action, branches=3, horizon=15, key=7))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert len(set(runs[0].round(9))) > 1  # the copies' futures differ
    stepped, reference = env.step(action)[0], untouched.step(action)[0]  # the snapshot itself was neither stepped nor reseeded
    assert all(np.array_equal(stepped[k], reference[k]) for k in stepped)
    figures = branch_calibration(model, "TaskAlloc/RBF-v0", [10_000], branches=2, stride=50)
    assert figures["branch_states"] == 2 and 0 <= figures["return_ceiling"] <= 1
    # A uniform actor: the second sampled decision differs from the executed one at every branched state.
    uniform = TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", **short, policy_kwargs={"heuristic_init": False})
    th.manual_seed(1)
    paired = branch_calibration(uniform, "TaskAlloc/RBF-v0", [10_000], branches=2, stride=50)
    assert paired["advantage_pairs"] == paired["branch_states"] == 2 and 0 <= paired["advantage_sign"] <= 1
    points = {k: np.array(paired.pop(k)) for k in ("state_points", "pair_points")}  # the plot's (Q, Ḡ) and (ΔQ, ΔḠ)
    assert points["state_points"].shape == points["pair_points"].shape == (2, 2)
    assert np.mean(np.sign(points["pair_points"][:, 0]) == np.sign(points["pair_points"][:, 1])) == paired["advantage_sign"]
    th.manual_seed(1)  # reproducible: the pairs draw from their own seeded stream
    again = branch_calibration(uniform, "TaskAlloc/RBF-v0", [10_000], branches=2, stride=50)
    assert all(np.array_equal(again.pop(k), v) for k, v in points.items())
    assert again == pytest.approx(paired, nan_ok=True)
    with pytest.raises(ValueError, match="branches"):
        branch_calibration(model, "TaskAlloc/RBF-v0", [10_000], branches=1)


def test_diagnose_reads_the_critic_against_the_reward_it_learns(monkeypatch):
    """A critic trained on the commitment reward is compared with returns of that reward, not of the env reward: on the
    same sampled episodes (diagnose seeds its sampling) only the critic's returns change. On 30-step episodes with
    γ = 0.7: 146 decisions, where 100 steps and γ = 0.9 take 488."""
    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.experiments.diagnose import diagnose

    monkeypatch.setattr(gym.spec("TaskAlloc/RBF-v0"), "max_episode_steps", 30)
    model = TwoStageSAC(
        "TAMPolicy", "TaskAlloc/RBF-v0", reward_timing="completion", seed=0, device="cpu", gamma=0.7,
        policy_kwargs={"hidden_dim": 16},
    )  # fmt: skip
    paid = diagnose(model, "TaskAlloc/RBF-v0", episodes=1, branches=0)
    model.reward_timing = "commitment"
    credited = diagnose(model, "TaskAlloc/RBF-v0", episodes=1, branches=0)
    assert paid.reward_timing == "completion" and credited.reward_timing == "commitment"
    assert credited.sampled_return == paid.sampled_return  # the same episodes, scored by the env reward
    assert credited.mc_return_mean != pytest.approx(paid.mc_return_mean, rel=1e-3)
    assert "credited at commitment" in credited.table()


def test_diagnose_cli_trains_on_n_envs(tmp_path, capsys):
    """``diagnose --algo-kwargs "{n_envs: 2}"`` trains on a VecEnv of 2 envs (the zoo's key), as ``learn`` does, and
    shows its branched episodes, the longest part, as a progress bar; the critic's plot is written beside the report."""
    import json

    from sb3_taskalloc.experiments.__main__ import main

    kwargs = "{n_envs: 2, learning_starts: 10, batch_size: 8, policy_kwargs: {hidden_dim: 8}}"
    args = ["diagnose", "--env", "EPT", "--steps", "40", "--episodes", "1", "--out", str(tmp_path), "--algo-kwargs", kwargs]
    main([*args, "--branches", "2", "--branch-stride", "25"])
    figures = json.loads((tmp_path / "diagnose_EPT-v0.json").read_text())
    assert figures["episodes"] == 1 and figures["branch_states"] == 4  # EPT's 100 steps, every 25th branched
    assert "branched episodes: 100%" in capsys.readouterr().err
    assert len(figures["state_points"]) == 4 and (tmp_path / "diagnose_EPT-v0.png").stat().st_size > 0  # its plot
    command = 'python -m sb3_taskalloc.experiments diagnose --env EPT --steps 40 --seed 0 --algo-kwargs \'{"n_envs": 2,'
    assert figures["command"].startswith(command) and figures["command"].endswith("--branches 2 --branch-stride 25")
    assert (tmp_path / "diagnose_EPT-v0.md").read_text().endswith(f"Command: `{figures['command']}`\n")
    with pytest.raises(SystemExit):
        main([*args, "--branches", "1"])  # no spread to measure with one rollout


def test_task_outcomes_classify_each_open_task():
    """Open tasks: kept, short of demand, covered without profit, no candidates; closed task slots are not counted."""
    from sb3_taskalloc.experiments.diagnose import task_outcomes

    obs = {
        "task_mask": np.array([1, 1, 1, 1, 0]),
        "entity_supply": np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]),
        "task_demand": np.array([[1.0, 1.0], [1.0, 1.0], [1.0, 1.0], [1.0, 0.0], [1.0, 0.0]]),
    }
    candidates = np.zeros((5, 3), dtype=bool)
    candidates[0, [0, 1]] = True  # covers task 0, kept
    candidates[1, 2] = False  # task 1: no candidates
    candidates[2, 0] = True  # task 2: entity 0 alone lacks the second resource
    candidates[3, 2] = True  # task 3: covered, but not kept (no profit)
    candidates[4, 2] = True  # task 4 is closed: not counted
    kept = np.array([True, False, False, False, False])
    assert task_outcomes(obs, candidates, kept).tolist() == [1, 1, 1, 1]
    candidates[2, 1] = True  # now 0 and 1 together cover task 2
    assert task_outcomes(obs, candidates, kept).tolist() == [1, 0, 2, 1]
