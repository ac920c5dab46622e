"""The experiment table's runner: its cells, budgets and digests, the zoo blocks it trains, its goal lines and the
Almighty figure (the smoke tables of every env: ``test_smoke_tables.py``; the learning experiment:
``test_learn_experiment.py`` and ``test_learn_command.py``; the diagnosis: ``test_diagnose.py``)."""

from __future__ import annotations

import csv
from typing import Any

import numpy as np
import pytest
import yaml

from sb3_taskalloc.experiments.table import TableRun
from tests.runner_helpers import record_distill_select


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


def test_one_seed_table_says_it_ranks_nothing(tmp_path):
    """A one-seed table ends with the warning that its columns carry no spread; a table of several seeds does not."""
    from sb3_taskalloc.experiments.table_report import ONE_SEED

    one = TableRun("RBF", 1, "smoke", tmp_path, progress=False)
    one.folder.mkdir(parents=True)
    for seed in range(2):
        one._record("Ours", "train", seed, "110", 0.0)
    assert one.write_table().read_text().rstrip().endswith(ONE_SEED)
    assert ONE_SEED not in TableRun("RBF", 2, "smoke", tmp_path, progress=False).write_table().read_text()


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


@pytest.mark.parametrize(("method", "last_save", "kill"), [("Ours", 24, 40), ("MaskablePPO", 16, 32)])
def test_a_model_killed_in_training_goes_on_from_its_checkpoint_exactly(tmp_path, monkeypatch, method, last_save, kill):
    """A table model's training is checkpointed as the learning experiment's seeds are: killed after a checkpoint, it
    goes on from it to the same weights, and its Monitor logs are cut back to the checkpoint and logged on, row for row
    those of an unstopped run."""
    import torch as th

    from sb3_taskalloc.experiments import checkpoint
    from sb3_taskalloc.experiments.budgets import Budget

    monkeypatch.setattr(Budget, "steps", lambda self, env, episodes: 48)  # 6 collections of 8 envs; 3 of PPO's 16 steps

    def table(out: Any) -> TableRun:
        return TableRun("EPT", 1, "smoke", out, methods=[method], progress=False)

    whole = table(tmp_path / "whole").trained(method, 0)
    stopped = table(tmp_path / "stopped")
    monkeypatch.setattr(checkpoint, "CHECKPOINT_SECONDS", 0.0)  # one at every collection
    save = checkpoint.TrainingCheckpoint.save

    def killed(self: Any) -> None:  # episodes of 4 steps end between the last checkpoint and the kill
        if self.model.num_timesteps >= kill:
            raise KeyboardInterrupt
        if self.model.num_timesteps <= last_save:
            save(self)

    with monkeypatch.context() as patch:
        patch.setattr(checkpoint.TrainingCheckpoint, "save", killed)
        with pytest.raises(KeyboardInterrupt):
            stopped.trained(method, 0)
    resumed = stopped.trained(method, 0)
    weights = zip(whole.policy.state_dict().values(), resumed.policy.state_dict().values(), strict=True)
    assert all(th.equal(a, b) for a, b in weights)

    def rows(out: Any) -> list[list[str]]:  # each env's episodes: return and length (not the wall-clock times)
        logs = sorted((out / "EPT" / "logs").glob("*.monitor.csv"))
        assert logs
        return [[",".join(r.split(",")[:2]) for r in log.read_text().splitlines()[2:]] for log in logs]

    assert rows(tmp_path / "stopped") == rows(tmp_path / "whole")
    assert not list((tmp_path / "stopped").rglob("*_training"))


def test_a_few_shot_training_killed_goes_on_from_its_checkpoint_exactly(tmp_path, monkeypatch):
    """The few-shot rows' further training is checkpointed too: killed, it goes on to the weights of an unstopped run."""
    import torch as th

    from sb3_taskalloc.experiments import checkpoint
    from sb3_taskalloc.experiments.budgets import Budget

    monkeypatch.setattr(Budget, "steps", lambda self, env, episodes: 48)  # training, then 48 more on the preset

    def few_shot(out: Any) -> Any:
        run = TableRun("EPT", 1, "smoke", out, methods=["Ours"], progress=False)
        run.cell("Ours", "few-shot (entity)", 0)
        return load_sac(run._model_path("Ours", 0, "few-shot (entity)"))

    whole = few_shot(tmp_path / "whole")
    monkeypatch.setattr(checkpoint, "CHECKPOINT_SECONDS", 0.0)
    save = checkpoint.TrainingCheckpoint.save

    def killed(self: Any) -> None:  # in the few-shot training (its steps count on from the trained model's 48)
        if self.model.num_timesteps >= 88:
            raise KeyboardInterrupt
        if self.model.num_timesteps <= 72:
            save(self)

    with monkeypatch.context() as patch:
        patch.setattr(checkpoint.TrainingCheckpoint, "save", killed)
        with pytest.raises(KeyboardInterrupt):
            few_shot(tmp_path / "stopped")
    resume, found = checkpoint.resume_training, []

    def recorded(*args: Any) -> Any:
        back = resume(*args)
        found.append(None if back is None else back[0].num_timesteps)
        return back

    monkeypatch.setattr(checkpoint, "resume_training", recorded)
    resumed = few_shot(tmp_path / "stopped")
    assert found[-1] == 72  # the few-shot training went on from its checkpoint
    assert resumed.num_timesteps == whole.num_timesteps == 96
    weights = zip(whole.policy.state_dict().values(), resumed.policy.state_dict().values(), strict=True)
    assert all(th.equal(a, b) for a, b in weights)


def load_sac(path: Any) -> Any:
    from sb3_taskalloc import TwoStageSAC

    return TwoStageSAC.load(path, device="cpu")
