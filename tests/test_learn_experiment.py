"""The learning experiment's runner: trained against untrained, the baselines and the planners per seed, its report,
resumption, worker processes and checkpoints (the command's later runs: ``test_learn_command.py``)."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.runner_helpers import record_distill_select


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
    iterations and its per-step MILP baseline show progress bars; without progress nothing is printed and no bar is asked
    for."""
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
        assert ("Almighty seed 0: per-step MILP" in printed.err) is progress  # minutes a seed on RBF


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


def check_reevaluations(run: Any, seeds: list[dict[str, Any]], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``run``'s saved models on another env and with other decoders: each report is written once, read back while its
    model and decisions are the same, and evaluated again where either changed (``seeds``: the run's own rows)."""
    import json

    from sb3_taskalloc.experiments import evaluation

    shifted = run.zero_shot("EPT-TaskShift").read_text()  # the saved models, untrained on another env
    assert "| seed | untrained | trained | Greedy |" in shifted and "trained ≥ Greedy:" in shifted
    searched = run.reevaluate(decoder="preassign_search", decoder_kwargs={"samples": 4})  # the same models, searching
    assert searched.name == "EPT_decoder_preassign_search_samples_4.md"
    assert "--decoder preassign_search --decoder-kwargs '{\"samples\": 4}'`" in searched.read_text()
    assert "| seed | untrained | trained | Greedy | MILP |" in searched.read_text()
    rows = json.loads(searched.with_suffix(".json").read_text())["seeds"]
    assert [r["MILP"] for r in rows] == [r["MILP"] for r in seeds]  # the seeds' own held-out episodes
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
        assert record["machine"]["cpu_capability"] and record["machine"]["libraries"]["stable-baselines3"]
    assert f"Measured on {data['seeds'][0]['machine']['cpu']} (" in text  # where the seeds' figures repeat
    assert (tmp_path / "EPT.png").stat().st_size > 0
    assert evaluation.eval_seeds(0, 10)[-1] < evaluation.eval_seeds(1, 10)[0]  # seeds' evaluation episodes never overlap
    check_reevaluations(run, data["seeds"], tmp_path, monkeypatch)
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


def test_a_seed_killed_after_training_is_evaluated_without_training_again(
    tmp_path, monkeypatch, short_branching, short_episodes
):
    """The trained model and its record so far are saved before the evaluations (the per-step MILP's take minutes on
    RBF): a seed stopped during them is evaluated from there, with the figures of a run that was not stopped."""
    import json

    from sb3_taskalloc.experiments import learn, learn_report

    kwargs = {"n_envs": 1, "learning_starts": 5, "batch_size": 8, "gamma": 0.7, "policy_kwargs": {"hidden_dim": 16}}

    def run(out: Path) -> Any:
        return learn.LearnRun("EPT", seeds=1, steps=10, eval_episodes=2, eval_every=5, algo_kwargs=kwargs, planners=(),
                              select_dagger=1, out=out)  # fmt: skip

    whole = run(tmp_path / "whole").run_seed(0)
    stopped = run(tmp_path / "stopped")
    with monkeypatch.context() as patch:
        patch.setattr(learn_report, "diagnose_record", lambda *a: (_ for _ in ()).throw(KeyboardInterrupt))
        with pytest.raises(KeyboardInterrupt):
            stopped.run_seed(0)
    trained = stopped.seed_path(0).with_name(stopped.seed_path(0).stem + "_trained.json")
    assert trained.exists() and trained.with_suffix(".zip").exists() and not stopped.seed_path(0).exists()
    monkeypatch.setattr("sb3_taskalloc.TwoStageSAC.learn", lambda *a, **k: pytest.fail("a trained seed was trained again"))
    monkeypatch.setattr("sb3_taskalloc.TwoStageSAC.distill_select", lambda *a, **k: pytest.fail("DAgger ran again"))
    resumed = stopped.run_seed(0)

    def figures(record: dict[str, Any]) -> str:  # the times of two runs differ
        return json.dumps({k: v for k, v in record.items() if not k.endswith("seconds")}, sort_keys=True)

    assert figures(resumed) == figures(whole) and resumed["train_seconds"] > 0
    assert not trained.exists() and not trained.with_suffix(".zip").exists()  # the finished seed's files replace them


@pytest.mark.parametrize("n_envs", [1, 2])
def test_a_seed_killed_in_training_goes_on_from_its_checkpoint_exactly(
    tmp_path, monkeypatch, short_branching, short_episodes, n_envs
):
    """A seed's training is checkpointed (model, buffer, envs mid-episode, random generators, curve): killed after a
    checkpoint, the seed goes on from it and its record repeats an unstopped run's to the digit."""
    import json

    from sb3_taskalloc.experiments import checkpoint, learn

    kwargs = {"n_envs": n_envs, "learning_starts": 3, "batch_size": 8, "gamma": 0.7, "policy_kwargs": {"hidden_dim": 16}}

    def run(out: Path) -> Any:
        return learn.LearnRun("EPT", seeds=1, steps=16, eval_episodes=2, eval_every=6, algo_kwargs=kwargs, planners=(),
                              select_dagger=0, out=out)  # fmt: skip

    whole = run(tmp_path / "whole").run_seed(0)  # no checkpoint in so short a run
    stopped = run(tmp_path / "stopped")
    monkeypatch.setattr(checkpoint, "CHECKPOINT_SECONDS", 0.0)  # one at every collection
    save = checkpoint.TrainingCheckpoint.save

    def killed_after_step_8(self: Any) -> None:
        save(self)
        if self.model.num_timesteps >= 8:
            raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(checkpoint.TrainingCheckpoint, "save", killed_after_step_8)
        with pytest.raises(KeyboardInterrupt):
            stopped.run_seed(0)
    folder = stopped.training_folder(0)
    assert json.loads((folder / "state.json").read_text())["step"] == "step_8" and not stopped.seed_path(0).exists()
    resumed = stopped.run_seed(0)

    def figures(record: dict[str, Any]) -> str:  # the times of two runs differ
        return json.dumps({k: v for k, v in record.items() if not k.endswith("seconds")}, sort_keys=True)

    assert figures(resumed) == figures(whole) and not folder.exists()
    assert saved_weights(stopped.seed_path(0).with_suffix(".zip")) == saved_weights(
        run(tmp_path / "whole").seed_path(0).with_suffix(".zip")
    )


def saved_weights(path: Path) -> list[list[float]]:
    """The weights of a saved model, as lists to compare exactly."""
    from sb3_taskalloc import TwoStageSAC

    return [p.flatten().tolist() for p in TwoStageSAC.load(path, device="cpu").policy.state_dict().values()]
