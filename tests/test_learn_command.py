"""The learning experiment's command on runs already made: DAgger after training, replicates on later seeds, further
held-out episodes, a CUDA run beside the CPU's, and the reports' names."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tests.runner_helpers import record_distill_select


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


def test_the_report_names_each_machine_once_and_the_gpu_where_a_seed_trained_on_it():
    from sb3_taskalloc.experiments.learn_report import machines

    cpu = {
        "cpu": "AMD EPYC",
        "cpu_capability": "AVX2",
        "gpu": "NVIDIA H100",
        "torch": "2.13.0",
        "libraries": {"stable-baselines3": "2.9.2"},
    }
    line = machines([{"machine": cpu}, {"machine": cpu}, {"machine": cpu, "device": "cuda"}, {"seed": 3}])
    assert line == (
        " Measured on AMD EPYC (AVX2) and NVIDIA H100, torch 2.13.0, stable-baselines3 2.9.2;"
        " AMD EPYC (AVX2), torch 2.13.0, stable-baselines3 2.9.2."
    )
    assert machines([{"seed": 0}]) == ""  # records of earlier versions carry no machine
