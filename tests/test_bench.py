"""``python -m sb3_taskalloc.bench``: each benchmark runs (``--quick``) and writes well-formed JSON.

Only the shape and sanity of the figures are checked here; the performance targets are measured by the benchmarks
themselves, never asserted by a timed test.
"""

from __future__ import annotations

import json
import math

import pytest
import torch

from sb3_taskalloc.experiments import bench


@pytest.mark.parametrize(
    "which, keys",
    [
        ("envs", {"env", "steps_per_s", "steps_per_s_gym_make", "deepcopy_ms", "entities"}),
        ("policy", {"device", "entities", "tasks", "predict_ms"}),
        ("train", {"device", "env", "config", "env_steps_per_s", "gradient_step_ms", "decision_ms", "replay_GB_for_100k"}),
        ("zoo", {"device", "env", "config", "env_steps_per_s", "gradient_step_ms", "decision_ms", "overrides"}),
        ("learn", {"device", "seed", "untrained", "target_return", "reached", "last_return", "training_s", "dagger_s"}),
        ("labels", {"labeller", "rounds", "tasks", "ms_per_round", "seconds"}),
    ],
)
def test_bench_quick_writes_json(tmp_path, capsys, which, keys):
    device = ["--device", "cpu"] if which == "policy" else []  # the device option, on one of the benchmarks it sets
    bench.main([which, "--quick", *device, "--out", str(tmp_path)])
    record = json.loads((tmp_path / f"bench_{which}.json").read_text())
    assert record["benchmark"] == which
    assert record["command"] == " ".join(["python -m sb3_taskalloc.bench", which, "--quick", *device, "--out", str(tmp_path)])
    assert record["machine"]["torch"]
    if device:
        assert {row["device"] for row in record["results"]} == {"cpu"}
    assert record["torch_threads"] == 1
    rows = record["results"]
    if which == "policy":  # first the latencies over the states of seeded episodes, then the reset-state rows
        episodes = [row for row in rows if "states" in row]
        names = {"TAMPolicy trained", "TAMPolicy untrained", f"TAMPolicy trained, search of {bench.SEARCH}", "Greedy",
                 f"TAMPolicy trained, team search of {bench.TEAM_SEARCH}", "TAMPolicy trained, exact covers",
                 "TAMPolicy trained, exact pre-assignment among each entity's top task",
                 "TAMPolicy trained, exact pre-assignment among each entity's top 2 tasks",
                 "TAMPolicy trained, exact pre-assignment among each entity's top 2 tasks, learned entity values"}  # fmt: skip
        assert {row["policy"] for row in episodes if row["env"] == "TaskAlloc/RBF-v0"} == names
        mt = [row for row in episodes if row["env"] == "TaskAlloc/MT-v0"]  # MT's recommended decoder beside the argmax
        assert [row["decoder"] for row in mt] == ["argmax", bench.MT_DECODER[0]]
        assert mt[1]["policy"] == "TAMPolicy untrained, exact pre-assignment among every pair, 64 % surcharge"
        # --quick: every eighth state of an episode's second half
        assert all(row["states"] >= 6 and 0 < row["median_ms"] <= row["p90_ms"] for row in episodes)
        rows = [row for row in rows if "states" not in row]
    assert rows and all(keys <= set(row) for row in rows)
    for row in rows:
        for key in keys:
            if key.endswith(("_per_s", "_ms", "_GB_for_100k")):
                assert row[key] > 0, (key, row)
    if which == "train":  # --quick times one block of learn(), recorded (rounded) beside the rate
        # what users run beside the defaults: RBF's zoo block (8 envs, its DAgger schedule extrapolated)
        assert [row["config"] for row in rows] == ["constructor defaults", "zoo block"]
        assert rows[1]["env"].endswith("zoo block (n_envs=8)") and rows[1]["dagger_iterations"] == 8
        assert rows[1]["minutes_for_the_block"] > 0
        for row in rows:
            (block,) = row["env_steps_per_s_blocks"]
            assert abs(block - row["env_steps_per_s"]) <= 0.005
        # AMIX's share of a gradient step, timed alone, and the rate it and the decision would allow; the zoo block
        # holds the pre-assign actor, whose critics do not train
        assert 0 < rows[0]["amix_ms_per_gradient_step"] < rows[0]["gradient_step_ms"]
        assert rows[0]["env_steps_per_s_bound"] == pytest.approx(
            1e3 / (rows[0]["decision_ms"] + rows[0]["amix_ms_per_gradient_step"])
        )
        assert rows[1]["amix_ms_per_gradient_step"] is None and rows[1]["env_steps_per_s_bound"] is None
    if which == "zoo":  # each env's recommended configuration, as users train it
        assert [row["env"].split(",")[0] for row in rows] == ["TaskAlloc/RBF-v0", "TaskAlloc/MT-v0"]
        assert all(row["config"] == "zoo block" and row["overrides"] == {} for row in rows)
    if which == "learn":  # --quick: 200 env steps, evaluated after 100 and 200 unless the target came first
        # one row per device: the CPU, and CUDA where torch sees a GPU (--device auto)
        assert [row["device"] for row in rows] == ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
        for row in rows:
            assert row["target_return"] == pytest.approx(bench.LEARN_TARGET * row["untrained"])
            steps = [point[0] for point in row["curve"]]
            n = row["n_envs"]  # the zoo config's: one vectorised step collects n env steps
            assert n == 8 and steps == [-(-100 // n) * n, 200][: len(steps)] and row["env_steps"] == steps[-1]
            assert row["reached"] == (row["last_return"] >= row["target_return"]) == (row["seconds_to_target"] is not None)
            assert row["curve"][-1][1] == row["training_s"] > 0
            # then the zoo block's DAgger phase, timed and evaluated apart (--quick: one iteration of one episode)
            assert row["dagger_iterations"] == 1 and row["dagger_s"] > 0 and math.isfinite(row["after_dagger_return"])
    if which == "labels":  # the two labellers on the same rounds: both exact, so equally profitable
        assert [row["labeller"] for row in rows] == ["task by task (branch and bound)", "one HiGHS solve per round"]
        assert rows[0]["rounds"] == rows[1]["rounds"] > 0 and rows[0]["tasks"] >= rows[0]["rounds"]
        assert rows[0]["max_profit_difference"] < 1e-4
        assert rows[0]["speedup"] == pytest.approx(rows[1]["seconds"] / rows[0]["seconds"])
    printed = capsys.readouterr().out
    assert printed.startswith(f"benchmark {which} (1 of 1): running\n")  # said before the minutes it may take
    assert f"## {which}" in printed  # the printed table


def test_bench_device_option(tmp_path, capsys):
    if not torch.cuda.is_available():
        with pytest.raises(SystemExit, match="--device cuda: no CUDA device"):
            bench.main(["policy", "--quick", "--device", "cuda", "--out", str(tmp_path)])


def test_bench_learn_rejects_bad_budgets(tmp_path):
    with pytest.raises(SystemExit, match="--learn-steps and --eval-every must be >= 1, got 0 and 4000"):
        bench.main(["learn", "--learn-steps", "0", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):  # argparse names the option
        bench.main(["learn", "--algo-kwargs", "[1, 2]", "--out", str(tmp_path)])


def test_table_has_every_column(capsys):
    bench._print_table("t", [{"a": 1.23456, "b": None}, {"a": 1234.5, "c": "x"}])
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[1] == "| a | b | c |"
    assert lines[3] == "| 1.23 |  |  |" and lines[4] == "| 1,234 |  | x |"
