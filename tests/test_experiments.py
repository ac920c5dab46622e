"""The experiment runners: the table's cells and budgets, the learning experiment, the diagnosis, the Almighty figure
(the smoke tables of every env: ``test_smoke_tables.py``)."""

from __future__ import annotations

import copy
import csv
import dataclasses
import math
import os
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import yaml

from sb3_taskalloc.experiments.table import TableRun


def record_distill_select(monkeypatch: pytest.MonkeyPatch) -> list[tuple[Any, dict[str, Any]]]:
    """Each call of ``TwoStageSAC.distill_select`` from here on, as (the rollouts' env, its keywords but the
    per-iteration callback)."""
    from sb3_taskalloc import TwoStageSAC

    calls: list[tuple[Any, dict[str, Any]]] = []
    real = TwoStageSAC.distill_select

    def recorded(self: TwoStageSAC, env: Any, callback: Any = None, **kw: Any) -> Any:
        calls.append((env, kw))
        return real(self, env, callback=callback, **kw)

    monkeypatch.setattr(TwoStageSAC, "distill_select", recorded)
    return calls


@pytest.fixture
def short_branching(monkeypatch: pytest.MonkeyPatch) -> None:
    """The learning experiment's diagnosis with 2 rollouts from every 20th state (8 from every 10th by default): the
    same figures, from fewer branches."""
    from functools import partial

    from sb3_taskalloc.experiments import diagnose

    monkeypatch.setattr(diagnose, "diagnose", partial(diagnose.diagnose, branches=2, branch_stride=20))


#: EPT's episode length in the runners' plumbing tests (registered: 100)
SHORT_EPT_STEPS = 12


def short_worker(parent: int) -> None:
    """The learning experiment's worker set-up (``jobs > 1``) with :data:`SHORT_EPT_STEPS`-step EPT episodes."""
    from sb3_taskalloc.experiments.evaluation import one_thread

    one_thread(parent)
    gym.spec("TaskAlloc/EPT-v0").max_episode_steps = SHORT_EPT_STEPS


@pytest.fixture
def short_episodes() -> Any:
    """EPT episodes of :data:`SHORT_EPT_STEPS` steps, here and in the learning experiment's worker processes: the
    runners' plumbing (files, columns, resumption) is the same on an eighth of an episode (the report test: 127 s at
    100 steps, 42 s at 25, 23 s at 12). A MonkeyPatch of its own, so that a test's ``monkeypatch.undo()`` keeps it."""
    from sb3_taskalloc.experiments import learn

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(gym.spec("TaskAlloc/EPT-v0"), "max_episode_steps", SHORT_EPT_STEPS)
        patch.setattr(learn, "one_thread", short_worker)
        yield


def test_digests_cover_the_codes_defaults(tmp_path, monkeypatch):
    """A changed code default (``RULE_LOGIT_SCALES``, a constructor default) files the Ours cells and the learning
    experiment's seeds under a new digest (they reused every earlier result); other methods' cells keep theirs."""
    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.experiments import budgets
    from sb3_taskalloc.experiments.learn import LearnRun
    from sb3_taskalloc.two_stage_sac import policies

    run = TableRun("RBF", 1, "smoke", tmp_path, progress=False)
    learn = LearnRun(env="RBF", out=str(tmp_path))
    before = run.cell_key("Ours", "train"), run.cell_key("Greedy", "train"), learn.key
    for patch in (
        lambda: monkeypatch.setattr(policies, "RULE_LOGIT_SCALES", (100.0, 20.0)),
        lambda: monkeypatch.setattr(TwoStageSAC.__init__, "__defaults__", (1e-3, *TwoStageSAC.__init__.__defaults__[1:])),
    ):
        patch()
        budgets.code_defaults.cache_clear()
        after = run.cell_key("Ours", "train"), run.cell_key("Greedy", "train"), learn.key
        assert after[0] != before[0] and after[1] == before[1] and after[2] != before[2]
        monkeypatch.undo()
    budgets.code_defaults.cache_clear()


def test_budgets_are_never_mixed(tmp_path):
    """Cells of one budget neither appear in nor stand in for another budget's table, and models are filed apart."""
    smoke = TableRun("EPT", 1, "smoke", tmp_path, methods=["Greedy"], progress=False)
    smoke._record("Greedy", "train", 0, "10.3", 0.0)
    local = TableRun("EPT", 1, "local", tmp_path, methods=["Greedy"], progress=False)
    assert smoke.done() == {("Greedy", "train", 0): "10.3"}
    assert local.done() == {}  # computed again under the local budget, not read from the smoke row
    assert local.cell_key("Greedy", "train") != smoke.cell_key("Greedy", "train")
    assert local._model_path("Ours", 0) != smoke._model_path("Ours", 0)
    local._record("Greedy", "train", 0, "132.1", 0.0)
    assert local.done() == {("Greedy", "train", 0): "132.1"} and smoke.done() == {("Greedy", "train", 0): "10.3"}
    assert "132.1" in local.write_table().read_text() and "10.3" not in local.write_table().read_text()


def test_cells_written_without_a_config_are_kept_but_not_used(tmp_path):
    """A cells file from before configurations were recorded keeps its rows (nothing a user saved is lost) and gains
    the column; its cells, of unknown settings, are computed again."""
    run = TableRun("EPT", 1, "smoke", tmp_path, methods=["Greedy"], progress=False)
    run.folder.mkdir(parents=True)
    run.cells_path.write_text("method,row,seed,value,seconds,budget\nGreedy,train,0,5.0,0.1,smoke\n")
    assert run.done() == {}
    run._record("Greedy", "train", 0, "7.0", 0.0)
    rows = list(csv.DictReader(run.cells_path.open()))
    assert [(r["value"], r["config"]) for r in rows] == [("5.0", ""), ("7.0", run.cell_key("Greedy", "train"))]


def test_table_trains_on_the_zoo_configs_n_envs(tmp_path, monkeypatch):
    """A zoo config with ``n_envs`` (rl-zoo3's key for vectorised collection) trains the TwoStageSAC columns on that many
    envs, each logging its episodes; the curves merge the logs, and the zero-shot and few-shot rows load the model on
    one env of another size."""
    from sb3_taskalloc.experiments import table, table_report

    zoo = table.zoo_hyperparameters
    monkeypatch.setattr(table, "zoo_hyperparameters", lambda env_id: {**zoo(env_id), "n_envs": 2})
    run = TableRun("RBF", 1, "smoke", tmp_path, methods=["Ours"], progress=False)
    run.run()
    model = run.trained("Ours", 0)
    assert model.n_envs == 2 and model.num_timesteps == run.budget.steps("RBF", run.budget.train_episodes)
    logs = table_report.env_logs(run._log_path("Ours", 0), 2)
    assert all(log.exists() for log in logs) and not run._log_path("Ours", 0).exists()
    per_env = [len(log.read_text().strip().splitlines()) - 2 for log in logs]
    assert len(table_report.logged_returns(logs)) == sum(per_env) > 0
    cells = {(r["row"]): r["value"] for r in csv.DictReader(run.cells_path.open())}
    assert all(np.isfinite(float(cells[row])) for row in ("train", "zero-shot (entity)", "few-shot (entity)"))
    few_shot = table_report.env_logs(run._log_path("Ours", 0, "few-shot (entity)"), 2)  # fine-tuned on 2 envs of the preset
    assert all(log.exists() for log in few_shot)
    assert (run.folder / "curves.png").exists()


def test_table_trains_w_o_pre_without_the_team_search(tmp_path, monkeypatch):
    """A zoo block with the team search (``select_kwargs["search_coef"]``, implementation detail 18, pre-assigning
    policies only) trains Ours with it and the W/o Pre columns, which decode from one shared pool, without it instead of
    failing."""
    from sb3_taskalloc.experiments import table

    zoo = table.zoo_hyperparameters
    monkeypatch.setattr(table, "zoo_hyperparameters", lambda env_id: {**zoo(env_id), "select_kwargs": {"search_coef": 1.0}})
    run = TableRun("RBF", 1, "smoke", tmp_path, progress=False)
    log = tmp_path / "log.monitor.csv"
    assert run._new_model(table.METHODS["Ours"], "TaskAlloc/RBF-v0", 0, log).select_kwargs["search_coef"] == 1.0
    pooled = run._new_model(table.METHODS["W/o Pre (sequence)"], "TaskAlloc/RBF-v0", 0, log)
    assert not pooled.policy.preassign and pooled.select_kwargs["search_coef"] == 0.0


def test_algo_kwargs_override_the_zoo_block_and_merge_its_policy_kwargs(tmp_path):
    """``--algo-kwargs`` go over the env's zoo block; a ``policy_kwargs`` override merges key by key, so that setting one
    policy keyword keeps the block's others (RBF's two rounds) and the run's key changes with it."""
    from sb3_taskalloc.experiments.learn import LearnRun
    from sb3_taskalloc.zoo_config import over_zoo, zoo_hyperparameters

    block = zoo_hyperparameters("TaskAlloc/RBF-v0")
    assert block["policy_kwargs"]["rounds"] > 1  # what the merge must keep
    merged = over_zoo(
        "TaskAlloc/RBF-v0",
        {"tau": 0.03, "policy_kwargs": {"n_critics": 3, "hidden_dim": 32}, "select_kwargs": {"batch_size": 8}},
    )
    assert merged["tau"] == 0.03 and merged["train_preassign_actor"] == block["train_preassign_actor"]
    assert merged["policy_kwargs"] == {**block["policy_kwargs"], "n_critics": 3, "hidden_dim": 32}
    assert merged["select_kwargs"] == {**block["select_kwargs"], "batch_size": 8}
    assert over_zoo("TaskAlloc/RBF-v0", {}) == block
    runs = [LearnRun("RBF", 1, 0, 1, 1000, kwargs, out=str(tmp_path)) for kwargs in ({}, {"policy_kwargs": {"rounds": 1}})]
    assert runs[0].hyperparameters == block and runs[1].hyperparameters["policy_kwargs"]["rounds"] == 1
    assert runs[0].key != runs[1].key
    rounds, block["policy_kwargs"]["rounds"] = block["policy_kwargs"]["rounds"], 99  # a caller's change stays its own
    assert zoo_hyperparameters("TaskAlloc/RBF-v0")["policy_kwargs"]["rounds"] == rounds
    # A callback entry (rl-zoo3's key) is not passed on to TwoStageSAC: the DAgger callback is zoo_dagger's, with the
    # callback's defaults filled in; any other callback, or keywords the callback refuses, are named.
    from sb3_taskalloc.zoo_config import DAGGER_CALLBACK, zoo_dagger

    config = tmp_path / "two_stage_sac.yml"

    def block(*callbacks: Any) -> None:
        config.write_text(
            yaml.safe_dump({"TaskAlloc/RBF-v0": {"policy": "TAMPolicy", "tau": 0.05, "callback": list(callbacks)}})
        )

    block({DAGGER_CALLBACK: {"iterations": 8, "imitation": "set"}})
    assert zoo_hyperparameters("TaskAlloc/RBF-v0", config) == {"tau": 0.05}
    defaults = {"episodes": 10, "epochs": 8, "learning_rate": 1e-3, "batch_size": 32}
    assert zoo_dagger("TaskAlloc/RBF-v0", config) == {"iterations": 8, "imitation": "set", **defaults}
    for entries, match in (
        (["stable_baselines3.common.callbacks.CheckpointCallback"], r"TaskAlloc/RBF-v0 has the callback .*CheckpointCallback"),
        ([{DAGGER_CALLBACK: {"iterations": 0}}], r"TaskAlloc/RBF-v0: .*iterations"),
        ([{DAGGER_CALLBACK: {"rounds": 2}}], r"TaskAlloc/RBF-v0: .*rounds"),
        ([{DAGGER_CALLBACK: {"seed": 3}}], "sets a seed"),
        ([DAGGER_CALLBACK, DAGGER_CALLBACK], "twice"),
    ):
        block(*entries)
        for read in (zoo_dagger, zoo_hyperparameters):
            with pytest.raises(ValueError, match=match):
                read("TaskAlloc/RBF-v0", config)
    for read in (zoo_dagger, zoo_hyperparameters):  # a block the file lacks is an error, not another configuration
        with pytest.raises(ValueError, match=r"has no block for 'TaskAlloc/EPT-v0'; it has \['TaskAlloc/RBF-v0'\]"):
            read("TaskAlloc/EPT-v0", config)
    with pytest.raises(FileNotFoundError, match="no zoo config at"):
        zoo_hyperparameters("TaskAlloc/RBF-v0", tmp_path / "missing.yml")
    assert zoo_dagger("TaskAlloc/EPT-v0") == {}  # the shipped EPT block has no DAgger


def test_learning_experiment_runs_the_zoo_blocks_dagger_callback(tmp_path, monkeypatch):
    """A zoo block's ``SelectDAggerCallback`` (:func:`.budgets.zoo_dagger`) is the learning experiment's DAgger phase
    unless ``select_dagger`` says otherwise: its iterations and loss become the run's, its other keywords reach
    ``distill_select`` and the seed's digest, the report's command writes them out, and 0 turns it off."""
    from sb3_taskalloc.experiments import learn

    zoo = {"iterations": 2, "episodes": 3, "epochs": 8, "learning_rate": 1e-3, "batch_size": 32, "imitation": "set"}
    monkeypatch.setattr(learn, "zoo_dagger", lambda env_id: dict(zoo))
    kwargs = {"learning_starts": 2, "batch_size": 4, "policy_kwargs": {"hidden_dim": 8}}

    def new_run(**dagger: Any) -> learn.LearnRun:
        return learn.LearnRun("Almighty", 1, steps=6, eval_episodes=2, eval_every=3, algo_kwargs=kwargs, planners=(),
                              out=tmp_path, **dagger)  # fmt: skip

    run, explicit, off = new_run(), new_run(select_dagger=2, dagger_imitation="set"), new_run(select_dagger=0)
    assert (run.select_dagger, run.dagger_imitation, run.dagger_kwargs) == (2, "set", {"episodes": 3})
    assert explicit.key == run.key and "--select-dagger 2 --dagger-imitation set" in run.command()
    assert "--select-dagger 0" in off.command()  # else the command would run the block's DAgger again
    monkeypatch.setattr(learn, "zoo_dagger", lambda env_id: {})
    assert new_run(select_dagger=2, dagger_imitation="set").key != run.key  # the block's episodes count
    assert new_run().select_dagger == 0 and new_run().key == off.key
    calls = record_distill_select(monkeypatch)
    record = run.run_seed(0)
    dagger = {"iterations": 2, "imitation": "set", "seed": learn.dagger_seed(0), "progress_bar": False, "episodes": 3}
    assert [kw for _, kw in calls] == [dagger]
    assert len(record["dagger"]) == 2 and [p[0] for p in record["curve"][-2:]] == [9, 12]  # 3 one-step episodes each


def test_learning_experiment_with_one_job_shows_the_seeds_phases(tmp_path, monkeypatch, capsys):
    """With one job (the default) the seed in progress says which phase it is in, and its training steps and DAgger
    iterations show progress bars; without progress nothing is printed and no bar is asked for."""
    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.experiments import learn

    bars: list[bool] = []
    real = TwoStageSAC.learn

    def recorded(self: TwoStageSAC, *args: Any, progress_bar: bool = False, **kw: Any) -> Any:
        bars.append(progress_bar)
        return real(self, *args, progress_bar=False, **kw)  # the bar itself is SB3's

    monkeypatch.setattr(TwoStageSAC, "learn", recorded)
    calls = record_distill_select(monkeypatch)
    kwargs = {"learning_starts": 2, "batch_size": 4, "policy_kwargs": {"hidden_dim": 8}}
    for progress, out in ((True, tmp_path / "a"), (False, tmp_path / "b")):
        run = learn.LearnRun("Almighty", 1, steps=6, eval_episodes=2, eval_every=3, algo_kwargs=kwargs, planners=(),
                             out=out, select_dagger=1)  # fmt: skip
        run.run(progress=progress)
        printed = capsys.readouterr()
        assert bars[-1] is progress and calls[-1][1]["progress_bar"] is progress
        phases = ["Almighty learning, seed 0 (1 of 1): training", "Almighty learning, seed 0: evaluating the trained"]
        assert all((phase in printed.out) is progress for phase in phases), printed.out
        assert ("select-stage DAgger" in printed.err) is progress


def test_learning_experiment_reports_no_critic_where_none_trained(tmp_path):
    """With the pre-assign actor held (``train_preassign_actor=False``) its critics do not train: the seed's record
    holds no critic figure (NaN), and the report has no critic column (every row as wide as the header's rule) and says
    so among the targets."""
    from sb3_taskalloc.experiments import learn

    kwargs = {"learning_starts": 2, "batch_size": 4, "policy_kwargs": {"hidden_dim": 8}, "train_preassign_actor": False}
    run = learn.LearnRun("Almighty", 1, steps=6, eval_episodes=2, eval_every=3, algo_kwargs=kwargs, planners=(),
                         out=tmp_path, select_dagger=0)  # fmt: skip
    record = run.run_seed(0)
    assert math.isnan(record["q_corr"]) and math.isnan(record["advantage_corr"]) and record["trained"]
    text = Path(run.run(progress=False)).with_suffix(".md").read_text()
    assert "- critic: not trained" in text and "corr(Q, G)" not in text
    rows = [line for line in text.splitlines() if line.startswith("|")]
    assert {row.count("|") for row in rows} == {rows[1].count("|")}  # no empty cell where the critic columns were


def test_table_runs_the_zoo_blocks_dagger_callback(tmp_path, monkeypatch):
    """A zoo block's ``SelectDAggerCallback`` runs after the training steps of the table's pre-assigning TwoStageSAC
    columns (W/o Pre shares one pool: none), under the budget's caps and on the budget's episodes, and enters the
    digests of those columns' cells and models only."""
    from sb3_taskalloc.experiments import table

    zoo = {"iterations": 4, "episodes": 10, "epochs": 8, "learning_rate": 1e-3, "batch_size": 32, "imitation": "set"}
    keys = {}
    for dagger in ({}, zoo):
        monkeypatch.setattr(table, "zoo_dagger", lambda env_id, dagger=dagger: dict(dagger))
        run = TableRun("RBF", 1, "smoke", tmp_path, methods=["Ours", "W/o Pre (sequence)"], progress=False)
        keys[bool(dagger)] = {name: run.cell_key(name, "train") for name in run.methods}
    assert keys[True]["Ours"] != keys[False]["Ours"] and keys[True]["W/o Pre (sequence)"] == keys[False]["W/o Pre (sequence)"]
    calls = record_distill_select(monkeypatch)
    run.trained("Ours", 0)
    run.trained("W/o Pre (sequence)", 0)
    # The smoke budget's caps over the block's, on the budget's episodes.
    ((env, kw),) = calls
    assert env.spec.max_episode_steps == run.budget.max_episode_steps
    assert (kw["iterations"], kw["episodes"], kw["epochs"], kw["imitation"]) == (1, 1, 1, "set")


def test_learn_workers_exit_when_their_parent_is_gone(tmp_path):
    """A ``learn --jobs N`` killed by a signal its workers do not receive leaves no worker training on: each worker
    (set up by ``one_thread``) exits once its parent is gone."""
    import subprocess
    import sys
    import time

    script = tmp_path / "parent.py"
    script.write_text(
        "import multiprocessing, os, time\n"
        "from concurrent.futures import ProcessPoolExecutor\n"
        "from sb3_taskalloc.experiments.evaluation import one_thread\n"
        "if __name__ == '__main__':\n"
        "    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context('spawn'), initializer=one_thread,\n"
        "                               initargs=(os.getpid(),))\n"
        "    print(pool.submit(os.getpid).result(), flush=True)\n"
        "    pool.submit(time.sleep, 600)\n"
        "    time.sleep(600)\n"
    )
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, cwd=Path.cwd())
    try:
        worker = int(parent.stdout.readline())  # type: ignore[union-attr]
    finally:
        parent.kill()
        parent.wait()

    def alive(pid: int) -> bool:  # a zombie (exited, not reaped by the container's init) counts as gone
        try:
            state = Path(f"/proc/{pid}/status").read_text().split("State:")[1].split()[0]
        except (FileNotFoundError, IndexError):
            return False
        return state != "Z"

    deadline = time.monotonic() + 30
    while alive(worker) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not alive(worker), f"worker {worker} still runs after its parent was killed"
    # A worker whose set-up runs only after the pool's process is gone (killed while the worker still imported torch)
    # is no longer that process's child: it exits at once rather than watching its new parent.
    late = subprocess.Popen(
        [sys.executable, "-c", "import os, time\nfrom sb3_taskalloc.experiments.evaluation import one_thread\n"
         f"one_thread({os.getpid() + 10**6})\ntime.sleep(600)\n"], cwd=Path.cwd(), stderr=subprocess.PIPE, text=True
    )  # fmt: skip
    try:
        _, errors = late.communicate(timeout=60)
        assert late.returncode == 1 and not errors, errors  # the watch's exit, not an error
    finally:
        late.kill()


def test_table_rejects_bad_arguments():
    with pytest.raises(ValueError, match="env"):
        TableRun("Foo", 1, "smoke")
    with pytest.raises(ValueError, match="budget"):
        TableRun("RBF", 1, "huge")
    with pytest.raises(ValueError, match="unknown methods"):
        TableRun("RBF", 1, "smoke", methods=["Ours", "Oracle"])


def test_almighty_figure(tmp_path):
    from sb3_taskalloc.experiments.almighty import VARIANTS, almighty_figure

    png = almighty_figure(seeds=1, steps=30, every=10, out=tmp_path)
    assert png.stat().st_size > 0
    rows = (tmp_path / "almighty.csv").read_text().strip().splitlines()
    assert rows[0] == "variant,seed,step,return" and len(rows) == 1 + len(VARIANTS) * 4  # steps 0, 10, 20, 30


def test_goal_lines_from_hand_written_cells(tmp_path):
    run = TableRun("MT", 1, "smoke", tmp_path, progress=False)
    run.folder.mkdir(parents=True)
    cells = {
        ("Ours", "train"): "120",
        ("GA", "train"): "100",
        ("PSO", "train"): "90",
        ("SOS", "train"): "-5",
        ("Greedy", "train"): "150",
        ("W/o Pre (sequence)", "train"): "80",
        ("Ours", "zero-shot (entity)"): "45",
        ("Ours", "from scratch (entity)"): "50",
        ("Ours", "zero-shot (task)"): "-30",
        ("Ours", "from scratch (task)"): "-20",
    }
    for (method, row), value in cells.items():
        run._record(method, row, 0, value, 0.0)
    text = run.write_table().read_text()
    assert "Ours / best planner (GA) on the training env: 1.200 (goal ≥ 1.1)" in text
    assert "Ours / Greedy on the training env: 0.800 (goal ≥ 1)" in text
    assert "Ours − W/o Pre (sequence) on the training env: +40.0 (goal > 0)" in text
    assert "W/o Pre (random)" not in text.split("Goals")[1]  # no cell, no line
    assert "Ours zero-shot / from scratch on the entity shift: 0.900 (goal ≥ 0.8)" in text
    assert "on the task shift: 0.667 (negative returns: reference cost / Ours' cost)" in text
    run._record("Greedy", "train", 0, "-10", 0.0)  # a later record of a cell replaces the earlier one
    assert "Ours / Greedy on the training env: n/a (signs differ: difference +130.0)" in run.write_table().read_text()


def test_goal_lines_use_only_the_tables_seeds(tmp_path):
    """Cells of a seed beyond the table's ``seeds`` (from a run with more seeds) enter neither the table nor its goals."""
    run = TableRun("RBF", 1, "smoke", tmp_path, progress=False)
    run.folder.mkdir(parents=True)
    for method, values in {"Ours": ("110", "50"), "Greedy": ("100", "100")}.items():
        for seed, value in enumerate(values):
            run._record(method, "train", seed, value, 0.0)
    assert "Ours / Greedy on the training env: 1.100 (goal ≥ 1)" in run.write_table().read_text()
    two = TableRun("RBF", 2, "smoke", tmp_path, progress=False)
    assert "Ours / Greedy on the training env: 0.800 (goal ≥ 1)" in two.write_table().read_text()


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


def test_learning_experiment_completes_records_of_earlier_versions(tmp_path, short_branching, short_episodes):
    """A finished seed whose critic figures predate ``critic_reward`` is measured again from its saved model when the
    critic learned the commitment reward, and kept with a warning when the model is gone; one without the stage
    columns gets them from the saved model."""
    import json

    from sb3_taskalloc.experiments import learn, learn_report

    kwargs = {"learning_starts": 5, "batch_size": 8, "reward_timing": "commitment", "policy_kwargs": {"hidden_dim": 16}}
    run = learn.LearnRun("EPT", 1, steps=10, eval_episodes=2, eval_every=5, algo_kwargs=kwargs, planners=(), out=tmp_path)
    record = run.run_seed(0)
    assert record["critic_reward"] == "commitment"
    path = run.seed_path(0)
    stale = {k: v for k, v in record.items() if k != "critic_reward"} | {"q_corr": 99.0}
    path.write_text(json.dumps(stale))
    again = run.run_seed(0)
    assert again["q_corr"] == pytest.approx(record["q_corr"]) and json.loads(path.read_text())["critic_reward"] == "commitment"
    path.write_text(json.dumps({k: v for k, v in record.items() if k not in ("actor_only", "pointer_only")}))
    assert run.run_seed(0)["pointer_only"] == record["pointer_only"] and "actor_only" in json.loads(path.read_text())
    # Without the figures against the expected return: measured by the same seeded diagnosis, the others unchanged.
    path.write_text(json.dumps({k: v for k, v in record.items() if k not in learn_report.CRITIC_BRANCHED} | {"q_corr": 99.0}))
    branched = run.run_seed(0)
    assert branched["q_corr_expected"] == pytest.approx(record["q_corr_expected"], nan_ok=True)
    assert branched["q_corr"] == pytest.approx(record["q_corr"])
    # Without the decision-pair figures (a later version): the same, and the table gains their columns.
    path.write_text(json.dumps({k: v for k, v in record.items() if k not in learn_report.CRITIC_ADVANTAGE}))
    paired = run.run_seed(0)
    assert paired["advantage_sign"] == pytest.approx(record["advantage_sign"], nan_ok=True)
    assert paired["q_corr_expected"] == pytest.approx(record["q_corr_expected"], nan_ok=True)
    assert "corr(ΔQ, ΔḠ)" in run.write([paired]).read_text()
    path.write_text(json.dumps(stale))
    path.with_suffix(".zip").unlink()
    with pytest.warns(UserWarning, match="is gone"):
        assert run.run_seed(0)["q_corr"] == 99.0


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


def test_resume_over_a_broken_model_file(tmp_path, capsys):
    """A model file cut short (a crash outside the runner) does not stop the resume: it is kept aside and the model is
    trained again."""
    run = TableRun("Almighty", 1, "smoke", tmp_path, methods=["Ours"], progress=False)
    path = run._model_path("Ours", 0)
    path.parent.mkdir(parents=True)
    path.write_bytes(b"PK\x03\x04 cut short")
    run.run()
    assert run.done()[("Ours", "train", 0)] != "" and path.exists()
    broken = list(path.parent.glob("*.broken-*.zip"))
    assert len(broken) == 1 and broken[0].read_bytes() == b"PK\x03\x04 cut short"
    assert "could not be loaded" in capsys.readouterr().out


def test_learning_experiment_reports_per_seed_and_resumes(tmp_path, monkeypatch, short_branching, short_episodes):
    """The learning experiment evaluates every column on the same held-out episodes per seed, writes per-seed and
    summary files, and a second run reads the finished seeds back instead of training again."""
    import json

    from sb3_taskalloc.experiments import evaluation, learn

    # n_envs: the zoo's 8; γ = 0.7: the diagnosis sums 13 steps past each episode's end (44 at 0.9, on 12-step episodes)
    kwargs = {"n_envs": 1, "learning_starts": 5, "batch_size": 8, "gamma": 0.7, "policy_kwargs": {"hidden_dim": 16}}
    run = learn.LearnRun(
        "EPT",
        seeds=2,
        steps=10,
        eval_episodes=2,
        eval_every=5,
        algo_kwargs=kwargs,
        planners=("GeneticAlgorithm",),
        out=tmp_path,
    )
    monkeypatch.setattr(evaluation, "PLANNER_BUDGET", {"population": 4, "budget": 8, "horizon": 2, "tail": 0})
    text = run.run(progress=False).read_text()
    header = "| seed | untrained | trained | only actor learned | only pointer learned | Greedy | MILP | GeneticAlgorithm |"
    assert header in text and "trained > Greedy:" in text
    assert "| scale Q/G | corr(Q, Ḡ) | scale Q/Ḡ | ceiling | corr(Q, free) | corr(Ḡ, free) | pairs |" in text
    assert "| pairs | tied | corr(ΔQ, ΔḠ) | ΔḠ ceiling | same sign | training s |" in text
    assert "a perfect critic would reach corr(Q, G)" in text
    assert f"the MILP stops at {learn.MILP_NODE_LIMIT} HiGHS nodes per solve" in text  # a stop by work, its gap reported
    data = json.loads((tmp_path / "EPT.json").read_text())
    assert [r["seed"] for r in data["seeds"]] == [0, 1]
    for record in data["seeds"]:
        assert set(record["eval_seeds"]).isdisjoint(range(10_000)) and len(record["trained"]) == 2
        assert len(record["actor_only"]) == len(record["pointer_only"]) == 2
        assert [p[0] for p in record["curve"]] == [0, 5, 10]
        assert record["MILP gap"]["solves"] > 0 and 0 <= record["MILP gap"]["max_gap"] < 1
    assert (tmp_path / "EPT.png").stat().st_size > 0
    assert evaluation.eval_seeds(0, 10)[-1] < evaluation.eval_seeds(1, 10)[0]  # seeds' evaluation episodes never overlap
    shifted = run.zero_shot("EPT-TaskShift").read_text()  # the saved models, untrained on another env
    assert "| seed | untrained | trained | Greedy |" in shifted and "trained ≥ Greedy:" in shifted
    searched = run.reevaluate(decoder="preassign_search", decoder_kwargs={"samples": 4})  # the same models, searching
    assert searched.name == "EPT_decoder_preassign_search_samples_4.md"
    assert "--decoder preassign_search --decoder-kwargs '{\"samples\": 4}'`" in searched.read_text()
    assert "| seed | untrained | trained | Greedy | MILP |" in searched.read_text()
    rows = json.loads(searched.with_suffix(".json").read_text())["seeds"]
    assert [r["MILP"] for r in rows] == [r["MILP"] for r in data["seeds"]]  # the seeds' own held-out episodes
    with monkeypatch.context() as patched:  # each seed's row was saved: a second call evaluates nothing again
        patched.setattr(evaluation, "episode_returns", lambda *a, **k: pytest.fail("a finished seed was evaluated again"))
        assert run.reevaluate(decoder="preassign_search", decoder_kwargs={"samples": 4}).read_text() == searched.read_text()
    saved = next(tmp_path.glob("EPT/EPT_decoder_preassign_search_samples_4_seed_0_*.json"))
    saved.write_text(json.dumps({**rows[0], "trained": [-1.0, -1.0], "model_digest": "another model"}))
    again = json.loads(
        run.reevaluate(decoder="preassign_search", decoder_kwargs={"samples": 4}).with_suffix(".json").read_text()
    )
    assert again["seeds"][0]["trained"] == rows[0]["trained"]  # a row of another model file is evaluated again
    assert again["decoder"] == "PreassignSearchDecoder(seed=0, samples=4, temperature=2.0)"
    from sb3_taskalloc.two_stage_sac.policies import TAMPolicy

    with monkeypatch.context() as patched:  # code that moves the decisions: the rows are stale
        patched.setattr(evaluation, "episode_returns", lambda *a, **k: pytest.fail("evaluated again"))
        run.reevaluate(decoder="preassign_search", decoder_kwargs={"samples": 4})  # the rows saved above
        decide = TAMPolicy._predict
        patched.setattr(TAMPolicy, "_predict", lambda self, *a, **k: decide(self, *a, **k) + 1)
        with pytest.raises(pytest.fail.Exception, match="evaluated again"):
            run.reevaluate(decoder="preassign_search", decoder_kwargs={"samples": 4})
    from sb3_taskalloc import TwoStageSAC

    model = TwoStageSAC.load(run.seed_path(0).with_suffix(".zip"), device="cpu")
    model.set_decoder("preassign_search", samples=4)
    assert json.loads(saved.read_text())["decisions"] == evaluation.decision_digest(model, "TaskAlloc/EPT-v0")
    assert evaluation.decision_digest(model, "TaskAlloc/EPT-v0") == evaluation.decision_digest(model, "TaskAlloc/EPT-v0")
    import sb3_taskalloc.two_stage_sac.decoding as decoding

    solved = []  # each task's exact cover of its candidates, solved at decision time
    cover_search = decoding.cover_search
    monkeypatch.setattr(decoding, "cover_search", lambda *a, **k: solved.append(1) or cover_search(*a, **k))
    exact = run.reevaluate(decoder="exact_covers")
    assert len(solved) > 0
    assert exact.name == "EPT_decoder_exact_covers.md" and "--decoder exact_covers`" in exact.read_text()
    # a setting with a decimal point names its report whole (Path.with_suffix would cut it at the dot)
    cooled = run.reevaluate(decoder="preassign_search", decoder_kwargs={"samples": 2, "temperature": 1.5})
    assert cooled.name == "EPT_decoder_preassign_search_samples_2_temperature_1.5.md"
    assert json.loads(cooled.with_name(cooled.stem + ".json").read_text())["decoder"].endswith("temperature=1.5)")
    with pytest.raises(ValueError, match="unknown decoding strategy"):
        run.reevaluate(decoder="beam")
    monkeypatch.setattr("sb3_taskalloc.TwoStageSAC", lambda *a, **k: pytest.fail("a finished seed was trained again"))
    assert run.run(progress=False).read_text() == text
    # Other algorithm settings train again but share the baselines, computed once per seed.
    monkeypatch.undo()
    monkeypatch.setattr(evaluation, "PLANNER_BUDGET", {"population": 4, "budget": 8, "horizon": 2, "tail": 0})
    monkeypatch.setattr("sb3_taskalloc.baselines.MILPAllocator", lambda *a, **k: pytest.fail("a baseline was run again"))
    other = learn.LearnRun(
        "EPT", seeds=2, steps=10, eval_episodes=2, eval_every=5, algo_kwargs={**kwargs, "n_envs": 2}, planners=(),
        out=tmp_path / "other",
    )  # fmt: skip
    for name in tmp_path.glob("EPT/baselines_*.json"):  # the same episodes and budgets: the same files
        (tmp_path / "other" / "EPT").mkdir(parents=True, exist_ok=True)
        (tmp_path / "other" / "EPT" / name.name).write_text(name.read_text())
    assert other.run_seed(0)["MILP"] == data["seeds"][0]["MILP"]
    # Seeds in worker processes (jobs=2): seed 0 is read back, seed 1 trains in a worker.
    monkeypatch.undo()
    summary = json.loads(other.run(progress=False, jobs=2).with_suffix(".json").read_text())
    assert [r["seed"] for r in summary["seeds"]] == [0, 1] and summary["seeds"][1]["MILP"] == data["seeds"][1]["MILP"]
    # n_envs = 2 (vectorised collection): the step count passes 5 at 6, and the curve is measured there.
    assert all([p[0] for p in r["curve"]] == [0, 6, 10] for r in summary["seeds"])


def test_learning_experiment_picks_the_best_checkpoint_on_validation_episodes(tmp_path, short_episodes):
    """With validation episodes the curve is measured on them (disjoint from the held-out episodes), the checkpoint of
    its best point after step 0 is saved and evaluated on the held-out episodes, and the summary reports it."""
    import json

    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.experiments import evaluation, learn

    kwargs = {"n_envs": 1, "learning_starts": 2, "batch_size": 4, "learning_rate": 0.05, "policy_kwargs": {"hidden_dim": 8}}
    run = learn.LearnRun("EPT", seeds=1, steps=12, eval_episodes=2, eval_every=4, algo_kwargs=kwargs, planners=(),
                         out=tmp_path, validation_episodes=2)  # fmt: skip
    plain = learn.LearnRun("EPT", seeds=1, steps=12, eval_episodes=2, eval_every=4, algo_kwargs=kwargs, planners=(),
                           out=tmp_path)  # fmt: skip
    assert run.key != plain.key  # a selected checkpoint is another result
    text = run.run(progress=False).read_text()
    assert "| trained | only actor learned | only pointer learned | best on validation | Greedy | MILP |" in text
    assert "best on validation / untrained (means):" in text and "--validation-episodes 2" in text
    (record,) = json.loads((tmp_path / "EPT.json").read_text())["seeds"]
    validation = evaluation.validation_seeds(0, 2)
    assert set(validation).isdisjoint(record["eval_seeds"]) and set(validation).isdisjoint(range(10_000))
    steps, values = zip(*record["curve"], strict=True)
    assert steps == (0, 4, 8, 12)
    best = int(np.argmax(values[1:])) + 1  # the first best point after step 0
    assert record["best_step"] == steps[best]
    model = TwoStageSAC.load(run.seed_path(0).with_name(run.seed_path(0).stem + "_best.zip"), device="cpu")
    assert np.mean(evaluation.episode_returns(model, run.env_id, validation)) == pytest.approx(values[best])
    assert evaluation.episode_returns(model, run.env_id, record["eval_seeds"]) == pytest.approx(record["best"])


def test_learning_experiment_teaches_the_pointer_by_dagger_after_training(tmp_path, monkeypatch):
    """``select_dagger``: DAgger follows the training steps (or the saved model of the same run without it, which is
    not trained again), the model before it is evaluated too, and its settings are part of the seed's digest."""
    import json

    from sb3_taskalloc.experiments import evaluation, learn
    from sb3_taskalloc.experiments.__main__ import main

    kwargs = {"learning_starts": 2, "batch_size": 4, "policy_kwargs": {"hidden_dim": 8}}
    plain = learn.LearnRun("Almighty", 1, steps=6, eval_episodes=2, eval_every=3, algo_kwargs=kwargs, planners=(),
                           out=tmp_path, validation_episodes=2)  # fmt: skip
    dagger = dataclasses.replace(plain, select_dagger=2)
    assert dagger.key != plain.key
    base = plain.run_seed(0)
    monkeypatch.setattr(learn.LearnRun, "_train", lambda *a: pytest.fail("the finished run without DAgger was trained again"))
    calls = record_distill_select(monkeypatch)
    text = dagger.run(progress=False).read_text()
    dagger = {"iterations": 2, "imitation": "sequence", "seed": learn.dagger_seed(0), "progress_bar": False}
    assert [kw for _, kw in calls] == [dagger]
    assert "| untrained | trained | before DAgger | only actor learned |" in text and "--select-dagger 2" in text
    (record,) = json.loads((tmp_path / "Almighty.json").read_text())["seeds"]
    assert record["before_dagger"] == base["trained"] and record["untrained"] == base["untrained"]
    # The curve goes on through DAgger, one point after each iteration at the env steps of its rollouts (one-step
    # episodes: 10 per iteration), on the validation episodes, where a better point would become the best checkpoint.
    assert record["curve"][:3] == [list(p) for p in base["curve"]] and len(record["dagger"]) == 2
    assert [p[0] for p in record["curve"][3:]] == [16, 26]
    assert record["best_step"] == base["best_step"] or record["best_step"] in (16, 26)
    assert record["train_seconds"] == pytest.approx(base["train_seconds"] + record["dagger_seconds"])
    # The curve's evaluations are timed apart from training: DAgger's points add to the time of the steps' points.
    assert 0 < base["curve_seconds"] < base["train_seconds"]
    assert base["curve_seconds"] < record["curve_seconds"] < base["curve_seconds"] + record["dagger_seconds"]
    assert "of which the curve's evaluations" in text
    assert learn.dagger_seed(0) > max(evaluation.validation_seeds(4, 100) + evaluation.eval_seeds(4, 100))
    # No training steps: DAgger alone, from the initial rule (the command line allows --steps 0 with --select-dagger).
    monkeypatch.undo()
    alone = learn.LearnRun("Almighty", 1, steps=0, eval_episodes=2, eval_every=3, algo_kwargs=kwargs, planners=(),
                           out=tmp_path / "alone", select_dagger=1)  # fmt: skip
    record = alone.run_seed(0)
    assert record["before_dagger"] == record["untrained"] and [p[0] for p in record["curve"]] == [0, 10]
    with pytest.raises(SystemExit):
        main(["learn", "--env", "Almighty", "--steps", "0", "--out", str(tmp_path / "cli")])
    for bad in (["--decision-exact-top", "-1"], ["--decision-exact-top", "2", "--decision-samples", "4"]):
        with pytest.raises(SystemExit):  # refused before any training
            main(["learn", "--env", "Almighty", "--steps", "1", "--out", str(tmp_path / "cli"), *bad])
    assert not (tmp_path / "cli").exists()


def test_learning_experiment_replicates_on_later_seeds(tmp_path):
    """``first_seed`` trains seeds ``first_seed`` .. ``first_seed + seeds − 1`` on their own held-out episodes (never
    those of seeds 0 .. first_seed − 1), names them in the report and its command, and bad values are refused. The
    report's critic means skip a seed that lacks a figure and say over how many seeds they are."""
    import json

    from sb3_taskalloc.experiments import evaluation, learn
    from sb3_taskalloc.experiments.__main__ import main

    kwargs = {"learning_starts": 2, "batch_size": 4, "policy_kwargs": {"hidden_dim": 8}}
    run = learn.LearnRun("Almighty", 2, steps=3, eval_episodes=2, eval_every=3, algo_kwargs=kwargs, planners=(),
                         out=tmp_path, first_seed=3)  # fmt: skip
    assert list(run.seed_range) == [3, 4]
    text = run.run(progress=False).read_text()
    assert "2 seeds (3–4) × 2 held-out episodes" in text and "--first-seed 3" in text
    records = json.loads((tmp_path / "Almighty.json").read_text())["seeds"]
    assert [r["seed"] for r in records] == [3, 4] and run.seed_path(3).with_suffix(".zip").exists()
    assert not any(tmp_path.glob("Almighty/seed_0_*"))
    assert [r["eval_seeds"] for r in records] == [evaluation.eval_seeds(3, 2), evaluation.eval_seeds(4, 2)]
    earlier = [s for seed in range(3) for s in evaluation.eval_seeds(seed, 100)]
    assert set(records[0]["eval_seeds"] + records[1]["eval_seeds"]).isdisjoint(earlier)
    assert "--first-seed" not in learn.LearnRun("Almighty", 2).command()
    # A seed whose sampled decisions never differed has no paired-critic figures: the means are over the other seeds.
    figures = {"advantage_pairs": 5, "advantage_ties": 1, "advantage_corr": 0.5, "advantage_ceiling": 0.9}
    figures["advantage_sign"] = 0.75
    none = {"advantage_pairs": 0, "advantage_ties": 0}
    none |= dict.fromkeys(["advantage_corr", "advantage_ceiling", "advantage_sign"], float("nan"))
    text = run.write([{**records[0], **figures}, {**records[1], **none}]).read_text()
    assert "corr(ΔQ, ΔḠ) 0.50 against a ceiling of 0.90" in text
    assert "75 % of the pairs whose returns differ (1 of the pairs returned the same in every branch) (means over" in text
    assert "| 2.5 | 0.5 | 0.50 (1 of 2 seeds) | 0.90 (1 of 2 seeds) | 0.75 (1 of 2 seeds) |" in text  # pairs: 5 and 0
    assert "nan" not in text.split("| mean ± std |")[1].split("\n")[0]
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="first_seed must be an integer ≥ 0"):
            learn.LearnRun("Almighty", 2, first_seed=bad)
    with pytest.raises(ValueError, match="seeds"):
        learn.LearnRun("Almighty", 0)
    with pytest.raises(SystemExit):
        main(["learn", "--env", "Almighty", "--first-seed", "-1", "--out", str(tmp_path / "cli")])
    assert not (tmp_path / "cli").exists()


def test_learning_experiment_evaluates_further_held_out_episodes(tmp_path, monkeypatch, capsys):
    """``more_episodes`` evaluates the finished models on the held-out reset seeds that follow the run's own (never
    another seed's), against Greedy only, and reports each seed over the run's and the further episodes, paired by
    episode; zero-shot, over the zero-shot re-evaluation's rows and the further ones; bad values are refused before
    any work."""
    import json

    import numpy as np

    from sb3_taskalloc.experiments import evaluation, learn
    from sb3_taskalloc.experiments.__main__ import main

    kwargs = {"learning_starts": 2, "batch_size": 4, "policy_kwargs": {"hidden_dim": 8}}
    run = learn.LearnRun("Almighty", 2, steps=3, eval_episodes=2, eval_every=3, algo_kwargs=kwargs, planners=(), out=tmp_path)
    run.run(progress=False)
    evaluated: list[tuple[int, ...]] = []
    returns = evaluation.episode_returns
    monkeypatch.setattr(
        evaluation,
        "episode_returns",
        lambda agent, env_id, seeds: evaluated.append(tuple(seeds)) or returns(agent, env_id, seeds),
    )
    monkeypatch.setattr("sb3_taskalloc.baselines.MILPAllocator", lambda *a, **k: pytest.fail("the MILP ran"))
    capsys.readouterr()
    path = run.reevaluate(more_episodes=3)
    assert "Almighty re-evaluation, 3 further held-out episodes per seed: 100%" in capsys.readouterr().err  # its bar
    assert path.name == "Almighty_more_episodes_3.md"
    assert sorted(set(evaluated)) == [tuple(evaluation.eval_seeds(seed, 5)[2:]) for seed in (0, 1)] and len(evaluated) == 6
    text = path.read_text()
    assert "3 further held-out episodes per seed" in text and "--more-episodes 3`" in text and "| MILP" not in text
    rows = json.loads(path.with_suffix(".json").read_text())["seeds"]
    for row in rows:
        own = json.loads(run.seed_path(row["seed"]).read_text())
        lead = np.array(own["trained"] + row["trained"]) - np.array(own["Greedy"] + row["Greedy"])
        trained = np.mean(own["trained"] + row["trained"])
        assert f"| {row['seed']} | 5 | " in text and f"| {trained:.1f} | " in text
        assert f"| {lead.mean():+.1f} ± {lead.std(ddof=1) / np.sqrt(5):.1f} |" in text
    assert "seeds over all episodes" in text
    with pytest.raises(FileNotFoundError, match="run the zero-shot re-evaluation first"):  # zero-shot: over its own rows
        run.reevaluate("Almighty", more_episodes=3)
    own = {row["seed"]: row for row in json.loads(run.zero_shot("Almighty").with_suffix(".json").read_text())["seeds"]}
    shifted = run.reevaluate("Almighty", more_episodes=3)
    assert shifted.name == "Almighty_zero_shot_Almighty_more_episodes_3.md"
    assert "zero-shot, 3 further episodes per seed" in shifted.read_text()
    for row in json.loads(shifted.with_suffix(".json").read_text())["seeds"]:
        lead = np.array(own[row["seed"]]["trained"] + row["trained"]) - np.array(own[row["seed"]]["Greedy"] + row["Greedy"])
        assert f"| {lead.mean():+.1f} ± {lead.std(ddof=1) / np.sqrt(5):.1f} |" in shifted.read_text()
    for bad, match in ((-1, "more_episodes must be a positive integer"), (True, "positive integer"), (99, "at most 100")):
        with pytest.raises(ValueError, match=match):
            run.reevaluate(more_episodes=bad)
    with pytest.raises(ValueError, match="no decoder"):
        run.reevaluate(decoder="team_search", more_episodes=2)
    monkeypatch.setattr(learn.LearnRun, "run", lambda *a, **k: pytest.fail("trained before the arguments were checked"))
    argv = ["learn", "--env", "Almighty", "--seeds", "1", "--steps", "3", "--eval-episodes", "2", "--out", str(tmp_path)]
    for more in ("-1", "99"):
        with pytest.raises(SystemExit):
            main([*argv, "--more-episodes", more])


def test_learning_experiment_on_cuda_is_a_run_of_its_own(tmp_path, capsys):
    """``device="cuda"`` trains on CUDA and evaluates on the CPU; its seed files have their own digest and its command and
    title name the device, so a CPU run never reuses them. Where CUDA is missing, the CLI refuses ``--device cuda`` before
    any training, and an unknown device is refused by name."""
    import json

    import torch as th

    from sb3_taskalloc.experiments import learn
    from sb3_taskalloc.experiments.__main__ import main

    kwargs = {"learning_starts": 2, "batch_size": 4, "policy_kwargs": {"hidden_dim": 8}}
    cpu = learn.LearnRun("Almighty", 1, steps=3, eval_episodes=2, eval_every=3, algo_kwargs=kwargs, planners=(), out=tmp_path)
    cuda = dataclasses.replace(cpu, device="cuda")
    assert cuda.key != cpu.key and cuda.seed_path(0) != cpu.seed_path(0)
    assert "--device cuda" in cuda.command() and "--device" not in cpu.command()
    with pytest.raises(ValueError, match="device must be 'cpu' or 'cuda', got 'tpu'"):
        learn.LearnRun("Almighty", 1, device="tpu")
    if not th.cuda.is_available():
        with pytest.raises(SystemExit):
            main(["learn", "--env", "Almighty", "--seeds", "1", "--device", "cuda", "--out", str(tmp_path / "cli")])
        assert "--device cuda: no CUDA device is available" in capsys.readouterr().err  # the same words as bench's
        assert not (tmp_path / "cli").exists()
        return
    text = cuda.run(progress=False).read_text()
    assert "(trained on CUDA)" in text and "--device cuda" in text
    (record,) = json.loads((tmp_path / "Almighty.json").read_text())["seeds"]
    assert record["device"] == "cuda" and len(record["trained"]) == 2
    assert cuda.seed_path(0).with_suffix(".zip").exists() and not cpu.seed_path(0).exists()


def test_a_sequence_setting_names_its_report_without_brackets():
    from sb3_taskalloc.experiments.reevaluate import _reevaluation_labels

    suffix, _, flags = _reevaluation_labels(None, "entity_value", {"top": 2, "theta": [-0.114, -0.041, 0.01]}, 0)
    assert suffix == "_decoder_entity_value_theta_-0.114_-0.041_0.01_top_2"
    assert """--decoder entity_value --decoder-kwargs '{"top": 2, "theta": [-0.114, -0.041, 0.01]}'""" in flags
