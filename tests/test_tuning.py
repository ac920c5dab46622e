"""Optuna sampler and study runner: valid models, pruning, shared journal studies, kill and restart."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import optuna
import pytest
import yaml
from optuna.trial import TrialState

from sb3_taskalloc import TwoStageSAC
from sb3_taskalloc.zoo_config import zoo_hyperparameters
from tuning import study as runner
from tuning.samplers import convert_two_stage_sac_params, sample_two_stage_sac_params

ROOT = Path(__file__).resolve().parents[1]
FIXED = {
    "learning_rate": 1e-3,
    "one_minus_gamma": 0.02,
    "tau": 0.01,
    "batch_size_pow": 4,
    "select_batch_size_pow": 3,
    "learning_starts": 0,
    "target_entropy_ratio": 0.2,
    "hidden_dim": 32,
    "n_attention_layers": 1,
    "prior_coef": 0.1,
    "select_prior_coef": 3.0,
    "logit_scale": 100.0,
    "select_logit_scale": 10.0,
    "rounds": 2,
    "select_search_coef": 10.0,
}


def test_sampler_under_fixed_trial_builds_a_valid_model():
    trial = optuna.trial.FixedTrial(FIXED)
    kwargs = sample_two_stage_sac_params(trial, 25, 1, {})
    assert kwargs == convert_two_stage_sac_params(FIXED)
    assert (
        kwargs["gamma"] == pytest.approx(0.98)
        and kwargs["batch_size"] == 16
        and kwargs["select_kwargs"] == {"prior_coef": 3.0, "search_coef": 10.0, "batch_size": 8, "search_samples": 32}
    )
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", seed=0, **kwargs)
    assert model.policy.hidden_dim == 32 and model.policy.n_attention_layers == 1 and model.gamma == pytest.approx(0.98)
    assert model.policy.rounds == 2 and model.select_kwargs["search_coef"] == 10.0
    model.learn(20)
    assert model._n_updates == 20


def test_sampled_values_stay_in_their_spaces():
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for _ in range(30):
        kwargs = sample_two_stage_sac_params(study.ask(), 25, 1, {})
        assert 0.9 <= kwargs["gamma"] <= 0.999 and 3e-5 <= kwargs["learning_rate"] <= 3e-3
        assert kwargs["batch_size"] in (16, 32, 64, 128) and kwargs["select_kwargs"]["batch_size"] in (4, 8, 16, 32)
        assert all(isinstance(v, int | float | str | bool | dict) for v in kwargs.values())  # pastes into YAML


def test_eval_callback_prunes_on_nan_and_on_the_pruner():
    study = optuna.create_study(pruner=optuna.pruners.ThresholdPruner(lower=1e9))  # prunes every report
    trial = study.ask()
    eval_env = gym.make("TaskAlloc/Almighty-v0")
    callback = runner.TrialEvalCallback(eval_env, trial, n_eval_episodes=1, eval_freq=5)
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", seed=0, learning_starts=100)
    model.learn(50, callback=callback)
    assert callback.is_pruned and model.num_timesteps == 5
    nan_env = gym.wrappers.TransformReward(gym.make("TaskAlloc/Almighty-v0"), lambda r: math.nan)
    callback = runner.TrialEvalCallback(nan_env, optuna.create_study().ask(), n_eval_episodes=1, eval_freq=5)
    model.learn(50, callback=callback)
    assert callback.is_pruned and np.isnan(callback.last_mean_reward)


def worker_args(tmp_path: Path, n_trials: int, n_timesteps: int = 40) -> list[str]:
    return [
        "--env", "TaskAlloc/Almighty-v0", "--n-trials", str(n_trials), "--n-timesteps", str(n_timesteps),
        "--n-evaluations", "2", "--eval-episodes", "1", "--n-startup-trials", "1", "--study-name", "s",
        "--storage", str(tmp_path / "s.log"), "--heartbeat-interval", "1", "--heartbeat-grace", "3",
    ]  # fmt: skip


def load(tmp_path: Path) -> optuna.Study:
    return optuna.load_study(study_name="s", storage=runner.make_storage(str(tmp_path / "s.log"), "s"))


def test_study_with_pruner_completes_and_summarizes(tmp_path):
    runner.main(worker_args(tmp_path, 2))
    study = load(tmp_path)
    assert runner.count(study, runner.FINISHED) == 2 and len(study.trials) == 2
    opened = runner.open_study(runner.parse_args(worker_args(tmp_path, 2)))
    assert isinstance(opened.pruner, optuna.pruners.MedianPruner) and isinstance(opened.sampler, optuna.samplers.TPESampler)
    assert len(opened.trials) == 2  # opened by name: the same study
    best = yaml.safe_load((tmp_path / "s/best.yml").read_text())["TaskAlloc/Almighty-v0"]
    # The env's zoo block with the best trial's settings over it, at the study's budget: it trains as the trial did.
    assert best["policy"] == "TAMPolicy" and best["n_envs"] == 1 and best["n_timesteps"] == 40
    assert best["learning_rate"] == study.best_trial.params["learning_rate"]
    assert best["learning_starts"] == study.best_trial.user_attrs["learning_starts"] <= 20
    rows = (tmp_path / "s/trials.csv").read_text().strip().splitlines()
    assert len(rows) == 3 and rows[0].startswith("number,state,value")
    # Resume by study name: a second run with a larger total adds only the missing trials.
    runner.main(worker_args(tmp_path, 3))
    assert runner.count(load(tmp_path), runner.FINISHED) == 3 and len(load(tmp_path).trials) == 3


def test_a_trial_trains_the_env_zoo_block_under_its_sampled_settings(monkeypatch):
    """The trials trained the constructor defaults on one env whatever the zoo block held; now MT's trial trains its
    block (8 envs, the margin rule, the held actor, the team search of 32 decodes) with the sampled settings over it."""
    from stable_baselines3.common.vec_env import VecEnv

    seen: dict[str, Any] = {}

    class StopError(Exception):
        pass

    def record(policy: str, env: Any, **kwargs: Any) -> None:
        seen.update(env=env, **kwargs)
        raise StopError

    monkeypatch.setattr(runner, "TwoStageSAC", record)
    args = runner.parse_args(["--env", "MT", "--n-timesteps", "800", "--n-evaluations", "2"])
    with pytest.raises(StopError):
        runner.objective(optuna.trial.FixedTrial({**FIXED, "learning_starts": 1000}), args)
    assert isinstance(seen["env"], VecEnv) and seen["env"].num_envs == 8
    assert seen["train_preassign_actor"] is False and seen["tau"] == 0.01  # the block's, and the sampled over it
    block = zoo_hyperparameters("TaskAlloc/MT-v0")["policy_kwargs"]  # the block's keywords, the sampled ones over them
    assert seen["policy_kwargs"] == {**block, "hidden_dim": 32, "n_attention_layers": 1, "logit_scale": 100.0,
                                     "select_logit_scale": 10.0, "rounds": 2}  # fmt: skip
    assert seen["select_kwargs"] == {"prior_coef": 3.0, "search_coef": 10.0, "search_samples": 32, "batch_size": 8}
    assert seen["learning_starts"] == 400  # at most half the trial's budget


def child_env() -> dict[str, str]:
    """This process's environment for a worker: one thread, and this checkout ahead of any ``PYTHONPATH`` it already has."""
    path = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    return {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": path}


def spawn(tmp_path: Path, n_trials: int, n_timesteps: int = 40) -> subprocess.Popen:
    env = child_env()
    return subprocess.Popen(
        [sys.executable, "-m", "tuning.study", *worker_args(tmp_path, n_trials, n_timesteps)],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip


def test_two_workers_share_one_journal(tmp_path):
    workers = [spawn(tmp_path, 6), spawn(tmp_path, 6)]
    for w in workers:
        out, _ = w.communicate(timeout=600)
        assert w.returncode == 0, out[-3000:]
    study = load(tmp_path)
    finished = study.get_trials(states=runner.FINISHED)
    assert len(finished) == 6
    assert len({t.number for t in finished}) == 6
    assert len({tuple(sorted(t.params.items())) for t in finished}) == 6  # no parameter set run twice
    assert all(t.state in (*runner.FINISHED, TrialState.FAIL) for t in study.trials)
    assert all(t.user_attrs.get("surplus") for t in study.trials if t.state == TrialState.FAIL)


def test_killed_worker_loses_no_completed_trial(tmp_path):
    worker = spawn(tmp_path, 2, n_timesteps=100)
    deadline = time.time() + 300
    while time.time() < deadline:  # kill it mid-trial, once at least one trial has completed
        time.sleep(0.2)
        if not (tmp_path / "s.log").exists():
            continue
        try:
            study = load(tmp_path)
        except KeyError:  # the journal's file exists a moment before the worker's record of the study in it
            continue
        running = study.get_trials(states=(TrialState.RUNNING,))
        # Mid-trial: the running trial has drawn all its parameters (it is training), so its retry must repeat them.
        if runner.count(study, runner.FINISHED) >= 1 and len(running) == 1 and len(running[0].params) == len(FIXED):
            worker.send_signal(signal.SIGKILL)
            break
    worker.wait(timeout=60)
    assert worker.returncode == -signal.SIGKILL, "the worker finished before it could be killed mid-trial"
    before = {t.number: t.value for t in load(tmp_path).get_trials(states=runner.FINISHED)}
    killed = [t for t in load(tmp_path).trials if t.state == TrialState.RUNNING]
    assert len(killed) == 1
    time.sleep(4)  # past the heartbeat grace period: the killed worker's trial is stale
    out, _ = spawn(tmp_path, 2, n_timesteps=100).communicate(timeout=600)
    study = load(tmp_path)
    after = {t.number: t.value for t in study.get_trials(states=runner.FINISHED)}
    assert {n: after[n] for n in before} == before  # every completed trial kept, with its value
    assert len(after) == 2
    assert study.trials[killed[0].number].state == TrialState.FAIL
    retried = [t for t in study.trials if t.user_attrs.get("retry_of") == killed[0].number]
    assert len(retried) == 1 and retried[0].params == killed[0].params and "re-queued" in out


def test_torn_journal_is_repaired_on_resume(tmp_path, capsys):
    """A journal whose last record was cut mid-write (a crash while writing) is repaired before anything is appended:
    every completed trial survives, the cut bytes are kept aside, and Optuna reads the file afterwards."""
    runner.main(worker_args(tmp_path, 2))
    journal = tmp_path / "s.log"
    complete = {t.number: t.value for t in load(tmp_path).get_trials(states=(TrialState.COMPLETE,))}
    size = journal.stat().st_size
    with journal.open("r+b") as f:
        f.truncate(size - 90)  # ``truncate -s -90``: the last record cut mid-line
    time.sleep(4)  # past the grace period: a trial whose closing record was cut is stale, and is run again
    runner.main(worker_args(tmp_path, 3))
    study = load(tmp_path)  # readable
    after = {t.number: t.value for t in study.get_trials(states=(TrialState.COMPLETE,))}
    assert {n: after[n] for n in complete if n in after} == {n: complete[n] for n in complete if n in after}
    assert len(complete) - len(set(complete) & set(after)) <= 1  # at most the record that was cut
    assert runner.count(study, runner.FINISHED) == 3
    torn = list(tmp_path.glob("s.log.torn-*"))
    assert len(torn) == 1 and 0 < torn[0].stat().st_size < 90 + 1
    assert "cut mid-write" in capsys.readouterr().out


def test_damaged_or_foreign_journal_is_refused_untouched(tmp_path):
    journal = tmp_path / "s.log"
    journal.write_text('{"op_code": 0}\nnot json\n{"op_code": 1}\n')
    with pytest.raises(SystemExit, match="line 2 is not a JSON record"):
        runner.main(worker_args(tmp_path, 1))
    assert journal.read_text() == '{"op_code": 0}\nnot json\n{"op_code": 1}\n'
    import sqlite3

    db = tmp_path / "s1.db"
    sqlite3.connect(db).execute("create table t (x)").connection.commit()
    args = [a if a != str(journal) else str(db) for a in worker_args(tmp_path, 1)]
    with pytest.raises(SystemExit, match="sqlite:///"):
        runner.main(args)


def test_unknown_journal_op_code_and_bad_storage_urls_are_named(tmp_path):
    """A journal record of an operation this Optuna does not know stopped the replay with "AssertionError: Should not
    reach."; an unknown URL scheme or a URL without ``//`` (which became a journal file in a folder ``sqlite:``) got
    SQLAlchemy's plugin error or no error at all."""
    journal = tmp_path / "s.log"
    journal.write_text('{"op_code": 0, "worker_id": "w", "study_name": "s", "directions": [1]}\n{"op_code": 99}\n')
    before = journal.read_text()
    with pytest.raises(SystemExit, match="line 2 has the operation code 99"):
        runner.main(worker_args(tmp_path, 1))
    assert journal.read_text() == before
    for url, match in [
        ("foo://host/db", "'foo' is not a database SQLAlchemy knows"),
        (f"sqlite:{tmp_path}/s.db", "looks like a URL without '//'"),
    ]:
        args = [a if a != str(journal) else url for a in worker_args(tmp_path, 1)]
        with pytest.raises(SystemExit, match=match):
            runner.main(args)
    assert not Path("sqlite:").exists()


def test_an_rdb_storage_retries_only_the_schema_race(tmp_path, monkeypatch):
    """Two workers opening an empty database together race to create Optuna's tables: the loser's ``already exists``
    (or unique violation) is retried and the tables the winner made are used; any other database error is raised at
    once, not hidden behind retries."""
    import sqlalchemy.exc

    from tuning import storage

    opened = storage.optuna.storages.RDBStorage
    errors = [sqlalchemy.exc.OperationalError("CREATE TABLE studies", {}, Exception("table studies already exists"))]

    def racing(*args: Any, **kwargs: Any) -> optuna.storages.RDBStorage:
        if errors:
            raise errors.pop()
        return opened(*args, **kwargs)

    monkeypatch.setattr(storage.optuna.storages, "RDBStorage", racing)
    monkeypatch.setattr(storage.time, "sleep", lambda seconds: None)
    url = f"sqlite:///{tmp_path / 's.db'}"
    assert isinstance(storage.make_storage(url, "s"), opened) and not errors
    errors.append(sqlalchemy.exc.OperationalError("SELECT 1", {}, Exception("unable to open database file")))
    with pytest.raises(sqlalchemy.exc.OperationalError, match="unable to open"):
        storage.make_storage(url, "s")
    assert not errors


def test_resuming_with_another_env_is_refused(tmp_path):
    runner.main(worker_args(tmp_path, 1))
    study = load(tmp_path)
    settings = study.user_attrs["settings"]
    assert settings["env"] == "TaskAlloc/Almighty-v0" and settings["n_timesteps"] == 40
    assert set(settings["search_space"]) >= {"learning_rate", "batch_size_pow"}
    args = worker_args(tmp_path, 2)
    args[args.index("TaskAlloc/Almighty-v0")] = "TaskAlloc/EPT-v0"
    with pytest.raises(SystemExit, match=r"other settings \(env"):
        runner.main(args)
    assert len(load(tmp_path).trials) == 1  # nothing added


def test_stale_trials_are_found_by_heartbeat_not_pid(tmp_path):
    """A running trial whose recorded pid is alive but unrelated (pid 1 in a container) and whose heartbeat stopped is
    failed and queued again; a trial with a recent heartbeat is left running whatever its pid."""
    study = optuna.create_study(study_name="s", storage=runner.make_storage(str(tmp_path / "s.log"), "s"))
    stale, live = study.ask({"x": optuna.distributions.FloatDistribution(0, 1)}), study.ask()
    for trial, beat in ((stale, time.time() - 600), (live, time.time())):
        trial.set_user_attr("pid", 1)
        trial.set_user_attr("host", "elsewhere")
        trial.set_user_attr("heartbeat", beat)
    assert runner.recover_stale_trials(study, grace_period=120) == [stale.number]
    states = {t.number: t.state for t in study.trials}
    assert states[stale.number] == TrialState.FAIL and states[live.number] == TrialState.RUNNING
    retry = [t for t in study.trials if t.user_attrs.get("retry_of") == stale.number]
    assert len(retry) == 1 and retry[0].state == TrialState.WAITING


def test_workers_joining_together_propose_different_parameters(tmp_path):
    """Two workers that open the study at the same moment (same state) proposed the same parameters when the seed
    came from the state the worker joined; seeded by trial number they differ, and a rerun proposes the same again."""
    args = runner.parse_args(worker_args(tmp_path, 4))
    first, second = runner.open_study(args), runner.open_study(args)
    one, two = first.ask(), second.ask()
    proposals = [sample_two_stage_sac_params(t, 0, 1, {}) for t in (one, two)]
    assert (one.number, two.number) == (0, 1) and proposals[0] != proposals[1]
    again = runner.open_study(runner.parse_args(worker_args(tmp_path / "again", 4)))
    assert sample_two_stage_sac_params(again.ask(), 0, 1, {}) == proposals[0]


def test_heartbeat_thread_beats_while_the_trial_runs():
    study = optuna.create_study()
    trial = study.ask()
    with runner.Heartbeat(trial, interval=0.05):
        first = study.trials[0].user_attrs["heartbeat"]
        time.sleep(0.3)
        assert study.trials[0].user_attrs["heartbeat"] > first


def test_outputs_go_next_to_the_journal(tmp_path, monkeypatch):
    """Started from another folder, a study writes its summaries beside its journal, not into the current folder."""
    elsewhere = tmp_path / "cwd"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    store = tmp_path / "store"
    args = [a if a != str(tmp_path / "s.log") else str(store / "s.log") for a in worker_args(tmp_path, 1)]
    runner.main(args)
    assert (store / "s" / "trials.csv").exists() and (store / "s" / "best.yml").exists()
    assert list(elsewhere.iterdir()) == []


def test_studies_are_reproducible_and_evaluate_every_trial_on_the_same_episodes(tmp_path, monkeypatch):
    """A study's sampler seed follows from --seed and the study's state (no process id): the same command on a new
    study proposes the same first trial. Every evaluation reseeds the evaluation env at the same seed, so trials are
    compared on the same episodes. The evaluation settings are part of the study's identity."""
    from stable_baselines3.common.vec_env import DummyVecEnv

    seeds: list[int | None] = []

    original = DummyVecEnv.seed
    monkeypatch.setattr(DummyVecEnv, "seed", lambda self, s=None: seeds.append(s) or original(self, s))
    runs = []
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        runner.main(worker_args(tmp_path / name, 1))
        runs.append(load(tmp_path / name).trials[0].params)
    assert runs[0] == runs[1]
    assert seeds.count(runner.EVAL_SEED) >= 4  # 2 evaluations per trial, 2 studies
    args = worker_args(tmp_path / "a", 2)
    args[args.index("--eval-episodes") + 1] = "2"
    with pytest.raises(SystemExit, match=r"other settings \(eval_episodes"):
        runner.main(args)


def test_a_running_worker_recovers_a_dead_workers_trial(tmp_path):
    """A worker that dies mid-trial leaves it RUNNING; a worker still running waits for its heartbeat to go stale, fails
    it, runs its parameters again and ends with every trial of the study finished (it used to end one short)."""
    runner.main(worker_args(tmp_path, 1))  # the study, with its settings recorded
    study = load(tmp_path)
    dead = study.ask()  # the dead worker's trial: a heartbeat now, never again
    dead.set_user_attr("heartbeat", time.time())
    runner.main(worker_args(tmp_path, 3))
    study = load(tmp_path)
    states = [t.state for t in study.trials]
    assert sum(s in runner.FINISHED for s in states) == 3
    assert study.trials[dead.number].state == optuna.trial.TrialState.FAIL
    assert any(t.user_attrs.get("retry_of") == dead.number for t in study.trials)
