"""learn() smoke tests: every env id × every ablation, vectorised envs, callbacks, logging (tiny budgets)."""

from __future__ import annotations

import inspect

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import CheckpointCallback, EvalCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import SubprocVecEnv

import envs
from sb3_taskalloc import SelectDAggerCallback, TwoStageSAC
from sb3_taskalloc.two_stage_sac.callbacks import dagger_seed
from sb3_taskalloc.two_stage_sac.two_stage_sac import DEFAULT_TOTAL_TIMESTEPS
from sb3_taskalloc.zoo_config import zoo_hyperparameters

ABLATIONS = {
    "full": {},
    "wo_pre_sequence": {"preassign": False, "task_order": "sequential"},
    "wo_pre_random": {"preassign": False, "task_order": "random"},
    "wo_amix": {"mixer": "global"},
    "wo_tam": {"encoder": "mlp"},
}


@pytest.mark.parametrize("env_id", list(envs.ENV_SPECS))
@pytest.mark.parametrize("ablation", list(ABLATIONS))
def test_learn_smoke(env_id, ablation):
    model = TwoStageSAC(
        "TAMPolicy", env_id, learning_starts=6, batch_size=4, seed=0, policy_kwargs={"hidden_dim": 8, **ABLATIONS[ablation]}
    )
    model.learn(10)
    assert model.num_timesteps == 10
    obs, _ = model.env.reset(), None  # type: ignore[union-attr]
    action, _ = model.predict(obs, deterministic=True)
    assert action.shape == (1, *model.action_space.shape)


def test_logger_keys(tmp_path):
    model = TwoStageSAC(
        "TAMPolicy", "TaskAlloc/Almighty-v0", learning_starts=4, batch_size=4, seed=0, policy_kwargs={"hidden_dim": 8}
    )
    model.set_logger(configure(str(tmp_path), ["csv"]))
    seen: set[str] = set()
    original = model.logger.record

    def record(key, value, exclude=None):
        seen.add(key)
        original(key, value, exclude)

    model.logger.record = record  # type: ignore[method-assign]
    model.learn(12, log_interval=1)
    keys = {"train/actor_loss", "train/critic_loss", "train/ent_coef", "train/ent_coef_loss", "train/select_actor_loss",
            "train/select_critic_loss", "rollout/ep_rew_mean"}  # fmt: skip
    assert keys <= seen, keys - seen


@pytest.mark.parametrize("vec_env_cls", [None, SubprocVecEnv])
def test_multiple_envs(vec_env_cls):
    kwargs = {"start_method": "fork"} if vec_env_cls is SubprocVecEnv else None
    env = make_vec_env("TaskAlloc/EPT-v0", n_envs=2, seed=0, vec_env_cls=vec_env_cls, vec_env_kwargs=kwargs)
    model = TwoStageSAC("TAMPolicy", env, learning_starts=6, batch_size=4, seed=0, policy_kwargs={"hidden_dim": 8})
    model.learn(16)
    assert model.num_timesteps == 16 and model.replay_buffer.n_envs == 2
    env.close()


def test_callbacks_and_progress_bar(tmp_path):
    model = TwoStageSAC(
        "TAMPolicy", "TaskAlloc/Almighty-v0", learning_starts=4, batch_size=4, seed=0, policy_kwargs={"hidden_dim": 8}
    )
    eval_cb = EvalCallback(
        Monitor(gym.make("TaskAlloc/Almighty-v0")), eval_freq=5, n_eval_episodes=2, log_path=str(tmp_path), verbose=0
    )
    ckpt = CheckpointCallback(save_freq=5, save_path=str(tmp_path / "ckpt"))
    model.learn(12, callback=[eval_cb, ckpt], progress_bar=True)
    assert (tmp_path / "evaluations.npz").exists()
    assert len(list((tmp_path / "ckpt").glob("*.zip"))) >= 2
    assert np.isfinite(eval_cb.last_mean_reward)


def test_select_dagger_callback_runs_distill_select_when_learn_ends(tmp_path):
    """:class:`SelectDAggerCallback` is ``distill_select`` after the SAC steps of the same ``learn`` call: the same
    pointer weights and figures as calling it by hand with the rollout seed :func:`dagger_seed` of the model's seed,
    each iteration logged under ``dagger/``; a later ``learn`` resets the training envs; bad arguments are refused
    when the callback is made, before training."""
    env_id = "TaskAlloc/Almighty-v0"

    def new_model() -> TwoStageSAC:
        return TwoStageSAC("TAMPolicy", make_vec_env(env_id, n_envs=2, seed=0), learning_starts=4, batch_size=4, seed=0,
                           device="cpu", policy_kwargs={"hidden_dim": 16})  # fmt: skip

    dagger = {"iterations": 2, "episodes": 8, "epochs": 2, "imitation": "set"}
    model = new_model()
    model.set_logger(configure(str(tmp_path), ["csv"]))
    callback = SelectDAggerCallback(**dagger)  # type: ignore[arg-type]
    model.learn(12, callback=callback)
    by_hand = new_model()
    by_hand.learn(12)
    trained = {k: v.clone() for k, v in by_hand.policy.selector.state_dict().items()}
    # By default the rollouts run on the episodes of the learning experiment's DAgger phase for the model's seed.
    assert by_hand.distill_select(env_id, seed=dagger_seed(0), **dagger) == callback.history  # type: ignore[arg-type]
    assert [h["iteration"] for h in callback.history] == [1.0, 2.0]
    taught = by_hand.policy.selector.state_dict()
    assert any(not th.equal(v, trained[k]) for k, v in taught.items()), "DAgger left the pointer as it was"
    for key, value in model.policy.selector.state_dict().items():
        assert th.equal(value, taught[key]), key
    logged = np.genfromtxt(tmp_path / "progress.csv", delimiter=",", names=True)
    assert list(logged["daggeriteration"][-2:]) == [1.0, 2.0]  # genfromtxt drops the "/" of "dagger/iteration"
    assert model._last_obs is None
    weights = {k: v.clone() for k, v in model.policy.selector.state_dict().items()}
    callback.on_training_end()  # rl-zoo3 calls it again after learn(): no second DAgger
    assert [h["iteration"] for h in callback.history] == [1.0, 2.0]
    assert all(th.equal(v, weights[k]) for k, v in model.policy.selector.state_dict().items())
    model.learn(4, reset_num_timesteps=False, callback=callback)  # a new learn() call runs it again
    assert model.num_timesteps == 16 and callback.history is not None and len(callback.history) == 2
    assert any(not th.equal(v, weights[k]) for k, v in model.policy.selector.state_dict().items())
    for bad in ({"iterations": 0}, {"imitation": "team"}, {"learning_rate": 0.0}, {"teacher": "entity_value"}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            SelectDAggerCallback(**bad)  # type: ignore[arg-type]
    unregistered = TwoStageSAC(
        "TAMPolicy", envs.AlmightyEnv(), learning_starts=4, batch_size=4, policy_kwargs={"hidden_dim": 16}
    )
    with pytest.raises(ValueError, match="registered training env"):
        unregistered.learn(4, callback=SelectDAggerCallback())
    assert unregistered.num_timesteps == 0  # refused when learn() starts, before any step
    almighty = TwoStageSAC("TAMPolicy", env_id, learning_starts=4, batch_size=4, policy_kwargs={"hidden_dim": 16})
    with pytest.raises(ValueError, match="no decoder was measured"):  # no recommended decoder: no teacher's costs
        almighty.learn(4, callback=SelectDAggerCallback(teacher="recommended"))
    assert almighty.num_timesteps == 0
    pooled = TwoStageSAC(
        "TAMPolicy", env_id, learning_starts=4, batch_size=4, policy_kwargs={"hidden_dim": 16, "preassign": False}
    )
    with pytest.raises(ValueError, match="pre-assigning policy"):
        pooled.learn(4, callback=SelectDAggerCallback())
    assert pooled.num_timesteps == 0


def test_select_dagger_callback_defaults_are_distill_selects():
    """The callback's keywords default to ``distill_select``'s, so a schedule written either way is the same DAgger."""
    from sb3_taskalloc.two_stage_sac import dagger

    parameters = inspect.signature(dagger.distill_select).parameters
    defaults = SelectDAggerCallback().kwargs
    assert defaults == {name: parameters[name].default for name in defaults}
    assert set(parameters) - set(defaults) == {"model", "env", "seed", "progress_bar", "callback"}


def test_default_budget_documented():
    assert "20,000" in TwoStageSAC.learn.__doc__  # type: ignore[operator]
    model = TwoStageSAC(
        "TAMPolicy", "TaskAlloc/Almighty-v0", learning_starts=DEFAULT_TOTAL_TIMESTEPS, policy_kwargs={"hidden_dim": 8}
    )
    model._setup_learn = lambda total_timesteps, *a, **k: pytest.fail(f"budget {total_timesteps}")  # type: ignore[method-assign]
    with pytest.raises(pytest.fail.Exception, match=f"budget {DEFAULT_TOTAL_TIMESTEPS}"):
        model.learn()


def test_device_auto_is_cpu_or_cuda():
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", device="auto", policy_kwargs={"hidden_dim": 8})
    assert model.device.type in ("cpu", "cuda")
    assert next(model.policy.parameters()).device.type == model.device.type


@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_learn_then_load_on_cpu(tmp_path):
    """Training runs on CUDA (buffers, entropy coefficients, optimizers there), and the saved model loads on the CPU
    with the same weights and the same pre-assignment probabilities."""
    kwargs = {"learning_starts": 10, "batch_size": 8, "seed": 0, "policy_kwargs": {"hidden_dim": 8}}
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", device="cuda", **kwargs)
    model.learn(24)
    assert {p.device.type for p in model.policy.parameters()} == {"cuda"}
    assert model.log_ent_coef is None or model.log_ent_coef.device.type == "cuda"
    model.save(tmp_path / "model")
    cpu = TwoStageSAC.load(tmp_path / "model", device="cpu")
    assert {p.device.type for p in cpu.policy.parameters()} == {"cpu"}
    for key, value in model.policy.state_dict().items():
        assert th.equal(value.cpu(), cpu.policy.state_dict()[key]), key
    obs, _ = gym.make("TaskAlloc/RBF-v0").reset(seed=1)
    assert model.policy.actor is not None and cpu.policy.actor is not None
    with th.no_grad():
        on_gpu = model.policy.actor(model.policy.parse(model.policy.obs_to_tensor(obs)[0])).probs.cpu()
        on_cpu = cpu.policy.actor(cpu.policy.parse(cpu.policy.obs_to_tensor(obs)[0])).probs
    th.testing.assert_close(on_gpu, on_cpu, atol=1e-5, rtol=1e-4)


def test_tensorboard_log(tmp_path):
    pytest.importorskip("tensorboard", reason="tensorboard is in the tests extra; install it to run this check")
    model = TwoStageSAC(
        "TAMPolicy", "TaskAlloc/Almighty-v0", learning_starts=4, batch_size=4, seed=0, tensorboard_log=str(tmp_path),
        policy_kwargs={"hidden_dim": 8},
    )  # fmt: skip
    model.learn(10, log_interval=1)
    runs = list(tmp_path.glob("TwoStageSAC_*"))
    assert runs and list(runs[0].glob("events.out.tfevents.*"))


def test_demo_dagger_follows_the_zoo_block():
    """The demo's DAgger is the env's zoo block's at the demo's budget: RBF's set loss on the pointer's own costs, and
    an env whose block has no DAgger still gets the set loss."""
    from sb3_taskalloc.experiments.demo import dagger_schedule

    rbf = dagger_schedule("TaskAlloc/RBF-v0", 3, 2)
    assert "teacher" not in rbf and rbf["imitation"] == "set" and (rbf["iterations"], rbf["episodes"]) == (3, 2)
    assert "teacher" not in dagger_schedule("TaskAlloc/MT-v0", 1, 1)
    assert dagger_schedule("TaskAlloc/EPT-v0", 1, 1) == {"imitation": "set", "iterations": 1, "episodes": 1}


def test_demo_writes_its_outputs(tmp_path, capsys, monkeypatch):
    """``make demo``'s entry point, on a short budget: it compares with the baselines and writes what it promises, and
    trains with the env's policy settings of its zoo block (MT's margin rule and two rounds). MT's episodes are cut to
    30 steps (registered: 150): the demo plays about ten of them."""
    import json

    from sb3_taskalloc.experiments import demo

    monkeypatch.setattr(gym.spec("TaskAlloc/MT-v0"), "max_episode_steps", 30)
    demo.main(
        ["--env", "MT", "--steps", "40", "--n-envs", "2", "--eval-episodes", "1", "--eval-every", "20",
         "--dagger-iterations", "1", "--dagger-episodes", "1", "--out", str(tmp_path)]
    )  # fmt: skip
    record = json.loads((tmp_path / "results.json").read_text())
    # From step 0 (the untrained policy), then EvalCallback's deterministic evaluations, in env steps.
    assert [step for step, _ in record["eval_curve"]] == [0, 20, 40]
    # then DAgger's rollouts, at the env steps they took; the paired gain over the held-out episodes is recorded
    assert len(record["dagger_curve"]) == 1 and record["dagger_curve"][0][0] > 40 and len(record["gain"]) == 2
    printed = capsys.readouterr().out
    assert record["gain"][1] is None and "(one episode)" in printed  # one episode has no standard error
    assert record["n_envs"] == 2 and len(list(tmp_path.glob("train/*.monitor.csv"))) == 2
    assert record["env"] == "TaskAlloc/MT-v0" and record["steps"] == 40 and record["dagger_iterations"] == 1
    assert set(record["eval"]) == {"TwoStageSAC", "TwoStageSAC untrained", "Greedy", "Random"}
    assert all(np.isfinite(mean) for mean, _ in record["eval"].values())
    for name in ("learning_curve.png", "episode.gif", "two_stage_sac.zip"):
        assert (tmp_path / name).stat().st_size > 0, name
    loaded = TwoStageSAC.load(tmp_path / "two_stage_sac.zip", device="cpu")
    assert loaded.num_timesteps == 40
    block = zoo_hyperparameters("TaskAlloc/MT-v0")["policy_kwargs"]  # the demo trains the zoo block's policy
    assert loaded.policy.rounds == block["rounds"] and loaded.policy.rule_weights == block["rule_weights"]
    assert loaded.policy.select_values is not None and loaded.policy.select_values.config == block["select_values"]
    assert "TwoStageSAC" in printed


@pytest.mark.parametrize("module", ["sb3_taskalloc.bench", "sb3_taskalloc.demo", "sb3_taskalloc.workers"])
def test_entry_points_answer_help(module):
    """The README's ``python -m`` commands reach their programs (the modules live under ``experiments/``)."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"usage: python -m {module}")


@pytest.mark.parametrize(
    ("module", "argv"),
    [
        ("sb3_taskalloc.experiments.__main__", ["almighty"]),
        ("sb3_taskalloc.experiments.__main__", ["table", "--env", "Almighty"]),
        ("sb3_taskalloc.experiments.__main__", ["learn", "--env", "Almighty"]),
        ("sb3_taskalloc.experiments.__main__", ["diagnose", "--env", "RBF"]),
        ("sb3_taskalloc.experiments.bench", ["envs"]),
        ("sb3_taskalloc.experiments.demo", []),
    ],
)
def test_clis_refuse_an_unwritable_out_before_any_work(tmp_path, module, argv):
    """A folder that cannot be written is named at once, not after minutes of work whose results it would lose."""
    import importlib

    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(SystemExit, match="cannot write to --out"):
        importlib.import_module(module).main([*argv, "--out", str(blocker / "sub")])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"batch_size": 0}, "batch_size must be a positive integer"),
        ({"batch_size": True}, "batch_size must be a positive integer, got True"),  # a bool is an int to Python
        ({"target_update_interval": 0}, "target_update_interval must be a positive integer"),
        ({"select_kwargs": {"batch_size": -1}}, r"select_kwargs\['batch_size'\] must be a positive integer"),
        ({"select_kwargs": {"batch": 4}}, r"select_kwargs: unknown settings \['batch'\]"),
        ({"select_kwargs": {"prior_coef": float("nan")}}, r"select_kwargs\['prior_coef'\] must be a finite number"),
        ({"train_preassign_actor": "no"}, "train_preassign_actor must be True or False, got 'no'"),
        ({"prior_coef": -0.5}, "prior_coef must be a finite number >= 0"),
        ({"target_entropy_ratio": "high"}, "target_entropy_ratio must be a finite number >= 0, got 'high'"),
        ({"ent_coef": "autox"}, "ent_coef must be 'auto'"),
        ({"ent_coef": "auto_x"}, "ent_coef must be 'auto'"),
        ({"ent_coef": -1.0}, "ent_coef must be"),
        ({"select_kwargs": {"ent_coef": float("nan")}}, r"select_kwargs\['ent_coef'\] must be"),
        ({"policy_kwargs": {"hidden_dim": 0}}, "hidden_dim must be a positive integer"),
        ({"policy_kwargs": {"hidden_dim": -4}}, "hidden_dim must be a positive integer"),
        ({"policy_kwargs": {"n_critics": 0}}, "n_critics must be a positive integer"),
        ({"policy_kwargs": {"heuristic_init": "false"}}, "heuristic_init must be True or False, got 'false'"),
        ({"policy_kwargs": {"preassign": "no"}}, "preassign must be True or False, got 'no'"),
        ({"policy_kwargs": {"pair_features": "no"}}, "pair_features must be True or False, got 'no'"),
        ({"policy_kwargs": {"mixer_kwargs": {"team_value": "no"}}}, r"mixer_kwargs\['team_value'\] must be True or False"),
        ({"policy_kwargs": {"mixer_kwargs": {"monotone": True}}}, r"mixer_kwargs: unknown settings \['monotone'\]"),
        ({"policy_kwargs": {"decision_samples": 8}}, r"policy_kwargs\['decision_samples'\]: .* decoding strategy"),
        ({"policy_kwargs": {"team_value": False}}, r"policy_kwargs\['team_value'\] is mixer_kwargs\['team_value'\] now"),
        ({"policy_kwargs": {"hiden_dim": 8}}, "TAMPolicy takes no keyword 'hiden_dim'"),
    ],
)
def test_bad_hyperparameters_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", **kwargs)


@pytest.mark.parametrize("steps", [-5, 2.5])
def test_bad_budget_is_named(steps):
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", policy_kwargs={"hidden_dim": 16})
    with pytest.raises(ValueError, match="total_timesteps must be a non-negative integer"):
        model.learn(steps)


def test_batched_decisions_equal_per_env_decisions():
    """Vectorised collection decides for all envs in one batched pass: deterministic decisions of a batch equal the
    decisions for each observation alone."""
    env = make_vec_env("TaskAlloc/RBF-v0", n_envs=4, seed=3)
    model = TwoStageSAC("TAMPolicy", env, seed=0, device="cpu", policy_kwargs={"hidden_dim": 16})
    obs = env.reset()
    for _ in range(3):
        batched, _ = model.predict(obs, deterministic=True)
        alone = np.stack([model.predict({k: v[i] for k, v in obs.items()}, deterministic=True)[0] for i in range(4)])
        assert np.array_equal(batched, alone)
        obs, *_ = env.step(batched)
    env.close()


def test_n_envs_save_load_resume(tmp_path):
    """With n_envs > 1: save, load with a VecEnv of the same size, and resume counting steps; the replay buffer keeps
    its per-env layout."""
    env = make_vec_env("TaskAlloc/EPT-v0", n_envs=2, seed=0)
    model = TwoStageSAC("TAMPolicy", env, learning_starts=6, batch_size=4, seed=0, policy_kwargs={"hidden_dim": 8})
    model.learn(12)
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer")
    loaded = TwoStageSAC.load(tmp_path / "model", env=make_vec_env("TaskAlloc/EPT-v0", n_envs=2, seed=1), device="cpu")
    loaded.load_replay_buffer(tmp_path / "buffer")
    assert loaded.replay_buffer.n_envs == 2 and loaded.replay_buffer.size() == model.replay_buffer.size()
    loaded.learn(8, reset_num_timesteps=False)
    assert loaded.num_timesteps == 20
    obs = loaded.get_env().reset()
    assert loaded.predict(obs, deterministic=True)[0].shape == (2, env.action_space.shape[0])
    # Another env count on load (SB3 allows it in load, not in set_env): one env, and a size-shifted preset.
    single = TwoStageSAC.load(tmp_path / "model", env=gym.make("TaskAlloc/EPT-v0"), device="cpu")
    assert single.n_envs == 1 and single.replay_buffer.n_envs == 1
    single.learn(4, reset_num_timesteps=False)
    shifted = TwoStageSAC.load(tmp_path / "model", env=gym.make("TaskAlloc/EPT-EntityShift-v0"), device="cpu")
    assert shifted.n_envs == 1
    with pytest.raises(AssertionError, match="number of environments"):
        single.set_env(make_vec_env("TaskAlloc/EPT-v0", n_envs=2))
