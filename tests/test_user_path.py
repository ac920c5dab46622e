"""What a user meets on the way: divergence stops training with its cause, Ctrl-C keeps the trained model, and no
command writes into the tracked ``results/`` unless asked."""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import optuna
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

import envs  # noqa: F401  (registers the TaskAlloc ids)
from sb3_taskalloc import SelectDAggerCallback, TwoStageSAC
from sb3_taskalloc.common.utils import DivergenceError, check_finite_parameters

SMALL = {"hidden_dim": 16}


def test_a_diverging_learning_rate_stops_training_with_its_cause():
    """``learning_rate=1e4`` used to leave NaN weights behind a normal-looking ``learn``: now it stops at the first
    non-finite loss or parameter, naming the step and what diverged, and nothing NaN is evaluated."""
    model = TwoStageSAC(
        "TAMPolicy", "TaskAlloc/Almighty-v0", learning_rate=1e4, learning_starts=8, batch_size=8, seed=0, policy_kwargs=SMALL
    )
    with pytest.raises(DivergenceError, match=r"training diverged (at|by) gradient step \d+ \(env step \d+\)"):
        model.learn(400)
    assert isinstance(DivergenceError("x"), FloatingPointError)


def test_the_logs_of_a_train_call_are_read_at_once_and_checked():
    """``train`` keeps each logged value as a tensor and reads them all on the host at the end of the call: the same
    floats, in order; a non-finite one is a divergence naming its key and the call's gradient steps."""
    from sb3_taskalloc.two_stage_sac.updates import read_logs

    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", seed=0, policy_kwargs=SMALL)
    model._n_updates = 6
    logs = {"critic_loss": [th.tensor(0.5), th.tensor(0.25), th.tensor(1 / 3)], "ent_coef": [th.tensor([0.1])] * 3}
    read = read_logs(model, logs, 3)
    assert read == {"critic_loss": [0.5, 0.25, th.tensor(1 / 3).item()], "ent_coef": [th.tensor(0.1).item()] * 3}
    logs["actor_loss"] = [th.tensor(1.0), th.tensor(math.nan), th.tensor(2.0)]
    with pytest.raises(DivergenceError, match=r"diverged in gradient steps 7–9 \(env step 0\): actor_loss = nan"):
        read_logs(model, logs, 3)
    with pytest.raises(DivergenceError, match=r"diverged at gradient step 7 .*: actor_loss = inf"):
        read_logs(model, {"actor_loss": [th.tensor(math.inf)]}, 1)


def test_a_non_finite_parameter_is_named():
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", learning_starts=8, batch_size=8, seed=0, policy_kwargs=SMALL)
    model.learn(12)
    check_finite_parameters({"selector": model.selector}, "here")  # finite: nothing raised
    with th.no_grad():
        next(model.selector.parameters()).view(-1)[0] = math.inf
    with pytest.raises(DivergenceError, match=r"parameter selector\.\S+ holds NaN or infinite values"):
        check_finite_parameters({"actor": model.actor, "selector": model.selector}, "here")
    with pytest.raises(DivergenceError, match="training diverged"):
        model.train(gradient_steps=1, batch_size=8)


def test_a_study_prunes_a_diverging_trial(monkeypatch, tmp_path):
    """The study's objective counts divergence as pruned, not as a finished trial with a return."""
    from tuning import study

    def diverge(self, *args, **kwargs):
        raise DivergenceError("training diverged at gradient step 3 (env step 10): critic_loss = nan")

    monkeypatch.setattr(TwoStageSAC, "learn", diverge)
    args = argparse.Namespace(env="TaskAlloc/Almighty-v0", env_kwargs=None, eval_episodes=1, n_timesteps=10,
                              n_evaluations=1, seed=0, device="cpu")  # fmt: skip
    trial = optuna.create_study().ask()
    with pytest.raises(optuna.TrialPruned, match="diverged"):
        study.objective(trial, args)


class _StopAt(BaseCallback):
    """Ends training after ``steps`` env steps, as Ctrl-C does inside rl-zoo3 (its ``learn`` returns early)."""

    def __init__(self, steps: int) -> None:
        super().__init__()
        self.steps = steps

    def _on_step(self) -> bool:
        return self.num_timesteps < self.steps


def _rbf_model() -> TwoStageSAC:
    return TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", learning_starts=8, batch_size=8, seed=0, policy_kwargs=SMALL)


def test_dagger_is_skipped_when_training_ended_early():
    """Training stopped before its budget (Ctrl-C in rl-zoo3, which then ends the callbacks and saves the model): the
    DAgger callback skips its iterations with a warning instead of delaying the save; ``after_interrupt=True`` runs
    them anyway."""
    model = _rbf_model()
    dagger = SelectDAggerCallback(iterations=1, episodes=1, epochs=1)
    with pytest.warns(UserWarning, match="training ended at env step 12 of 40: SelectDAggerCallback skips DAgger"):
        model.learn(40, callback=[_StopAt(12), dagger])
    assert dagger.history == []
    again = SelectDAggerCallback(iterations=1, episodes=1, epochs=1, after_interrupt=True)
    model.learn(40, callback=[_StopAt(12), again])
    assert len(again.history) == 1
    with pytest.raises(ValueError, match="after_interrupt must be True or False"):
        SelectDAggerCallback(after_interrupt="no")  # type: ignore[arg-type]


@pytest.mark.parametrize("asked", ["learn(progress_bar=True)", "SB3's bar in the list (rl-zoo3's -P)", "no bar"])
def test_the_progress_bar_closes_before_dagger_and_dagger_shows_its_own(monkeypatch, asked):
    """A DAgger callback under a progress bar: SB3's bar is closed when the steps end, before DAgger's minutes begin (SB3
    alone closes it after every callback), and DAgger shows its own; without a bar, neither."""
    from stable_baselines3.common.callbacks import ProgressBarCallback

    events: list[tuple[str, bool | None]] = []
    real_end, real_distill = ProgressBarCallback._on_training_end, TwoStageSAC.distill_select

    def bar_closed(self):
        events.append(("SB3 bar closed", None))
        real_end(self)

    def distill(self, env, **kwargs):
        events.append(("DAgger", kwargs["progress_bar"]))
        return real_distill(self, env, **kwargs)

    monkeypatch.setattr(ProgressBarCallback, "_on_training_end", bar_closed)
    monkeypatch.setattr(TwoStageSAC, "distill_select", distill)
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", learning_starts=8, batch_size=8, seed=0, policy_kwargs=SMALL)
    model.zoo_callbacks, later = [SelectDAggerCallback(iterations=1, episodes=1, epochs=1)], _StopAt(10**6)
    given: list[BaseCallback] = [later, ProgressBarCallback()] if asked.startswith("SB3") else [later]
    model.learn(16, callback=given, progress_bar=asked.startswith("learn"))
    assert events == ([("DAgger", False)] if asked == "no bar" else [("SB3 bar closed", None), ("DAgger", True)])
    assert later.n_calls == 16  # the caller's callback still ran beside the zoo's


def test_ctrl_c_during_dagger_keeps_the_iterations_done(monkeypatch):
    """Ctrl-C during DAgger stops it; the callback returns normally (so the caller saves the model) with the
    iterations done."""
    model = _rbf_model()
    real = TwoStageSAC.distill_select

    def interrupted(self, env, **kwargs):
        done = kwargs.pop("callback")
        real(self, env, callback=done, **{**kwargs, "iterations": 1})
        raise KeyboardInterrupt

    monkeypatch.setattr(TwoStageSAC, "distill_select", interrupted)
    dagger = SelectDAggerCallback(iterations=3, episodes=1, epochs=1)
    with pytest.warns(UserWarning, match="DAgger interrupted after 1 of 3 iterations"):
        model.learn(16, callback=dagger)
    assert len(dagger.history) == 1
    obs, _ = gym.make("TaskAlloc/RBF-v0").reset(seed=0)
    assert np.isfinite(model.predict(obs, deterministic=True)[0]).all()


class _CtrlCAt(BaseCallback):
    """Raises KeyboardInterrupt at env step ``steps``, as Ctrl-C does in a user's own script."""

    def __init__(self, steps: int) -> None:
        super().__init__()
        self.steps = steps

    def _on_step(self) -> bool:
        if self.num_timesteps >= self.steps:
            raise KeyboardInterrupt
        return True


@pytest.mark.parametrize("where", ["env step", "gradient step"])
def test_ctrl_c_in_learn_leaves_a_model_that_saves_and_trains_on(tmp_path, monkeypatch, where):
    """Ctrl-C in ``model.learn`` (between env steps, or inside a gradient step before its optimizer steps) ends the
    call with KeyboardInterrupt, as in SB3; ``model`` holds what it learned so far: it saves, loads to the same
    decisions and learns on from the step it reached (the README's quick start relies on it)."""
    model = _rbf_model()
    callback = None
    if where == "env step":
        callback = _CtrlCAt(20)
    else:
        real, calls = th.optim.Adam.step, []

        def interrupted(self, *args, **kwargs):  # the fifth optimizer step of training is interrupted
            calls.append(1)
            if len(calls) == 5:
                raise KeyboardInterrupt
            return real(self, *args, **kwargs)

        monkeypatch.setattr(th.optim.Adam, "step", interrupted)
    with pytest.raises(KeyboardInterrupt):
        model.learn(40, callback=callback)
    monkeypatch.undo()
    reached = model.num_timesteps
    assert 8 < reached < 40
    model.save(tmp_path / "m")
    loaded = TwoStageSAC.load(tmp_path / "m", device="cpu")
    obs, _ = gym.make("TaskAlloc/RBF-v0").reset(seed=3)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    updates = model._n_updates
    model.learn(8, reset_num_timesteps=False)
    assert model.num_timesteps == reached + 8 and model._n_updates > updates


def test_no_command_writes_into_results_by_default():
    """Every command's output folder defaults to ``runs/`` (or another gitignored folder): ``results/`` holds the
    committed reports and changes only when ``--out`` asks for it."""
    from sb3_taskalloc.experiments import __main__ as experiments
    from sb3_taskalloc.experiments import bench, cotrain, demo
    from sb3_taskalloc.experiments.learn import LearnRun
    from sb3_taskalloc.experiments.table import TableRun

    parser = experiments.build_parser()
    commands = {
        "table": ["table", "--env", "RBF"],
        "almighty": ["almighty"],
        "diagnose": ["diagnose", "--env", "RBF"],
        "learn": ["learn", "--env", "RBF"],
    }
    outs = {name: parser.parse_args(argv).out for name, argv in commands.items()}
    outs["workers"] = cotrain.build_parser().parse_args([]).out
    outs["demo"] = demo.parse_args([]).out
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        outs["bench"] = bench.build_parser().parse_args(["envs"]).out
    outs["LearnRun"] = str(LearnRun("RBF").out)
    outs["TableRun"] = str(TableRun("RBF", 1, "smoke").folder.parent)
    ignored = ("runs", "demo_out")
    assert all(str(out).split("/")[0] in ignored for out in outs.values()), outs


def test_a_budget_within_the_warm_up_is_announced():
    """``learn`` shorter than ``learning_starts`` runs no gradient step: it says so instead of returning the untrained
    model as if trained."""
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/EPT-v0", policy_kwargs=SMALL)
    with pytest.warns(UserWarning, match=r"learn\(200\) ends at env step 200, within the warm-up \(learning_starts=500\)"):
        model.learn(200)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.learn(400, reset_num_timesteps=False)  # ends at 600, past the warm-up: trains, no warning


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"gamma": float("nan")}, "gamma must be a finite number > 0"),
        ({"gamma": 1.5}, r"gamma must lie in \(0, 1\]"),
        ({"tau": 0.0}, "tau must be a finite number > 0"),
        ({"target_entropy_ratio": -0.1}, "target_entropy_ratio must be a finite number >= 0"),
        ({"learning_rate": float("inf")}, "learning_rate must be a finite number >= 0"),
        ({"learning_starts": -1}, "learning_starts must be an integer ≥ 0"),
        ({"replay_buffer_class": dict}, "replay_buffer_class must be TwoStageReplayBuffer or a subclass"),
    ],
)
def test_numeric_settings_are_range_checked_at_construction_and_at_load(tmp_path, kwargs, match):
    with pytest.raises(ValueError, match=match):
        TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", policy_kwargs=SMALL, **kwargs)
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", policy_kwargs=SMALL)
    model.save(tmp_path / "m.zip")
    with pytest.raises(ValueError, match=match):
        TwoStageSAC.load(tmp_path / "m.zip", **kwargs)


def test_saved_files_get_the_usual_mode(tmp_path):
    """An atomic save writes a temporary file first; the file in place has the mode of any new file, not mkstemp's
    0600."""
    import os

    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", policy_kwargs=SMALL)
    umask = os.umask(0o022)
    try:
        model.save(tmp_path / "m.zip")
    finally:
        os.umask(umask)
    assert (tmp_path / "m.zip").stat().st_mode & 0o777 == 0o644
    assert [p.name for p in tmp_path.iterdir()] == ["m.zip"]


def test_commands_take_env_names_in_both_forms_and_show_defaults(capsys):
    from sb3_taskalloc.experiments import __main__ as experiments
    from sb3_taskalloc.experiments import demo

    args = experiments.build_parser().parse_args(["learn", "--env", "TaskAlloc/MT-v0", "--zero-shot", "MT-EntityShift"])
    assert (args.env, args.zero_shot) == ("MT", "MT-EntityShift")
    for command in ("learn", "diagnose"):  # a shifted env's own block is measured on it
        assert experiments.build_parser().parse_args([command, "--env", "TaskAlloc/MT-TaskShift-v0"]).env == "MT-TaskShift"
    with pytest.raises(SystemExit):
        experiments.build_parser().parse_args(["learn", "--env", "MT-Nope"])
    assert demo.parse_args(["--env", "RBF"]).env == "TaskAlloc/RBF-v0"
    with pytest.raises(SystemExit):
        experiments.build_parser().parse_args(["learn", "--help"])
    assert "(default: runs/learn)" in " ".join(capsys.readouterr().out.split())


def test_from_zoo_is_the_recommended_configuration():
    """One call gives an env's zoo block: its keywords, its envs, its budget as learn()'s default and its DAgger."""
    from sb3_taskalloc.zoo_config import zoo_hyperparameters

    model = TwoStageSAC.from_zoo("TaskAlloc/RBF-v0", seed=0, _init_setup_model=False)
    block = zoo_hyperparameters("TaskAlloc/RBF-v0")
    assert model.n_envs == block["n_envs"] == 8 and model.tau == block["tau"] and not model.train_preassign_actor
    assert model.select_kwargs["search_coef"] == block["select_kwargs"]["search_coef"] and model.zoo_n_timesteps == 18_000
    assert model.policy_kwargs["rounds"] == 4
    assert [type(c).__name__ for c in model.zoo_callbacks] == ["SelectDAggerCallback"]
    assert model.zoo_callbacks[0].kwargs["iterations"] == 8
    small = TwoStageSAC.from_zoo(
        "TaskAlloc/Almighty-v0", seed=0, n_timesteps=30, learning_starts=10, policy_kwargs={"hidden_dim": 16}
    )
    assert small.learning_rate == pytest.approx(1e-3) and small.policy.hidden_dim == 16 and small.zoo_callbacks == []
    small.learn()  # the overridden budget of the block
    assert small.num_timesteps == 30 and small._n_updates > 0
    with pytest.raises(ValueError, match="has no block for 'TaskAlloc/Nope-v0'"):
        TwoStageSAC.from_zoo("TaskAlloc/Nope-v0")


def test_dagger_without_pre_assignment_is_refused_before_training(monkeypatch, capsys):
    from sb3_taskalloc.experiments import __main__ as experiments
    from sb3_taskalloc.experiments.learn import LearnRun

    monkeypatch.setattr(LearnRun, "run", lambda *a, **k: pytest.fail("trained before the arguments were checked"))
    with pytest.raises(SystemExit):
        experiments.main(["learn", "--env", "RBF", "--algo-kwargs", "{policy_kwargs: {preassign: false}}"])
    assert "with preassign: false give --select-dagger 0" in capsys.readouterr().err


def test_a_rerun_of_the_workers_leaves_no_stale_figures(tmp_path):
    from sb3_taskalloc.experiments.cotrain import save_history

    history = [{"manager_income": 1.0, "worker_income": 2.0, "total_income": 3.0, "mean_bid": 0.2, "picked_bids": 4.0}]
    assert {p.name for p in save_history(history, tmp_path, "t")} == {"incomes.csv", "incomes.png"}
    assert save_history([], tmp_path, "t") == [] and not list(tmp_path.glob("incomes.*"))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"reward_scale": 1e5}, r"observations up to .* \(task reward × reward_scale"),
        ({"travel_cost": 1e6}, r"observations up to .* \(entity cost \+ travel_cost"),
        ({"max_entities": float("nan")}, "max_entities must be an integer, got nan"),
    ],
)
def test_env_settings_that_leave_the_observation_space_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        gym.make("TaskAlloc/RBF-v0", **kwargs)


def test_unclear_tracebacks_became_messages(tmp_path, capsys):
    """A missing model file, a model of another algorithm, malformed YAML on a command line and zero seeds each give a
    message naming what is wrong."""
    from sb3_contrib import MaskablePPO

    from sb3_taskalloc.experiments import __main__ as experiments

    with pytest.raises(FileNotFoundError, match=r"no saved model at \S*nothing \(nor \.zip\)"):
        TwoStageSAC.load(tmp_path / "nothing")
    MaskablePPO("MultiInputPolicy", gym.make("TaskAlloc/Almighty-v0"), n_steps=16, batch_size=16).save(tmp_path / "ppo.zip")
    with pytest.raises(
        ValueError, match="holds a model with a MaskableMultiInputActorCriticPolicy policy, not a TwoStageSAC model"
    ):
        TwoStageSAC.load(tmp_path / "ppo.zip")
    for argv, match in (
        (["learn", "--env", "RBF", "--algo-kwargs", "{tau: [0.05"], "not valid YAML"),
        (["learn", "--env", "RBF", "--zero-shot", "Foo"], "--zero-shot: unknown env 'Foo'"),  # refused after training
        (["almighty", "--seeds", "0"], "--seeds, --steps and --every must be >= 1"),
    ):
        with pytest.raises(SystemExit):
            experiments.main(argv)
        assert match in capsys.readouterr().err


@pytest.mark.parametrize(
    ("policy_kwargs", "match"),
    [
        ({"n_attention_layers": -1}, "n_attention_layers must be an integer ≥ 0"),
        ({"activation_fn": "relu"}, "activation_fn must be a torch.nn.Module class"),
    ],
)
def test_bad_policy_settings_are_named(policy_kwargs, match):
    with pytest.raises(ValueError, match=match):
        TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", policy_kwargs=policy_kwargs)


def test_an_sb3_policy_name_is_answered_with_the_one_this_algorithm_takes():
    with pytest.raises(ValueError, match="TwoStageSAC has no policy 'MlpPolicy': it takes TAMPolicy"):
        TwoStageSAC("MlpPolicy", "TaskAlloc/Almighty-v0")


def test_a_kill_during_a_save_leaves_no_lasting_temporary_file(tmp_path):
    import os
    import time

    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", policy_kwargs=SMALL)
    stale, fresh = tmp_path / ".m.abc.tmp.zip", tmp_path / ".m.def.tmp.zip"  # as a killed save leaves them
    for path in (stale, fresh):
        path.write_bytes(b"partial")
    os.utime(stale, (time.time() - 7200, time.time() - 7200))
    model.save(tmp_path / "m.zip")
    assert not stale.exists() and fresh.exists()  # a recent one may be another process's save in progress


def test_table_recomputes_a_model_whose_weights_are_damaged(tmp_path, capsys):
    import zipfile

    from sb3_taskalloc.experiments.table import METHODS, TableRun

    run = TableRun("Almighty", 1, "smoke", tmp_path, progress=False)
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", policy_kwargs=SMALL)
    path = tmp_path / "model.zip"
    model.save(path)
    with zipfile.ZipFile(path) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, b"damaged" if name == "policy.pth" else data)
    assert run._load_saved(METHODS["Ours"], path) is None
    assert not path.exists() and len(list(tmp_path.glob("model.broken-*.zip"))) == 1
    assert "could not be loaded" in capsys.readouterr().out


def test_the_advertised_call_takes_an_env_id_without_importing_envs():
    """``TwoStageSAC("TAMPolicy", "TaskAlloc/MT-v0")`` in a fresh interpreter that never imported ``envs``: importing
    sb3_taskalloc registers the ids, where gymnasium alone would answer "Namespace TaskAlloc not found"."""
    code = (
        "import sys\n"
        "from sb3_taskalloc import TwoStageSAC\n"
        "model = TwoStageSAC('TAMPolicy', 'TaskAlloc/MT-v0', seed=0, device='cpu')\n"
        "print(model.env.num_envs, 'envs' in sys.modules)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["1", "True"]
