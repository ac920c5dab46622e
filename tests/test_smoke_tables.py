"""The experiment table's smoke runs: every env's table well formed, resumed after an interruption cell by cell.

The tables are computed once (a session fixture, about 30 s) and read by every test here; ``tests/conftest.py``
sends this module's tests to one pytest-xdist worker, so that no second worker computes them again.
"""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import gymnasium as gym
import pytest

from sb3_taskalloc.experiments.budgets import ENVS, METHODS, ROWS
from sb3_taskalloc.experiments.table import TableRun

CELL = re.compile(r"^(-?\d+(\.\d+)?( ± \d+(\.\d+)?)?|n/a \((size|static|scratch)\))$")  # one seed: no spread


def run_smoke(env: str, out: Path) -> Path:
    """``env``'s smoke table under ``out`` (the cells already there are read back, not computed again)."""
    return TableRun(env, 1, "smoke", out, progress=False).run()


def read_table(text: str) -> list[list[str]]:
    """The rows of a markdown table's ``text``, cell by cell."""
    lines = [line for line in text.splitlines() if line.startswith("| ")]
    return [[c.strip() for c in line.strip("|").split("|")] for line in lines]


@pytest.fixture(scope="session")
def smoke_tables(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("results")
    # In this process, one env after the other: under pytest-xdist the other worker runs the rest of the suite beside
    # it (a pool of two spawned interpreters cost about 12 s of CPU more on CI's two cores). Session-scoped, and this
    # module's tests go to one worker (conftest's scheduler), so it is computed once per run.
    for env in ENVS:
        run_smoke(env, out)
    return out


@pytest.mark.parametrize("env", ENVS)
def test_smoke_table_is_well_formed(smoke_tables, env):
    text = (smoke_tables / env / "table.md").read_text()
    table = read_table(text)
    assert table[0] == ["setting", *METHODS]
    rows = [r[0] for r in table[1:]]
    assert rows == (["train"] if env == "Almighty" else ROWS)
    for row in table[1:]:
        assert len(row) == len(METHODS) + 1 and all(CELL.match(c) for c in row[1:]), row
    with (smoke_tables / env / "table.csv").open() as f:
        records = list(csv.DictReader(f))
    assert {r["method"] for r in records} == set(METHODS)
    train = {r["method"]: r for r in records if r["row"] == "train"}
    assert all(train[m]["mean"] != "n/a" for m in METHODS)  # every method runs on the training env
    if env != "Almighty":
        # Size-specific methods transfer only where the preset keeps the entity count (EPT's other tower table does).
        resized = (
            gym.make(f"TaskAlloc/{env}-v0").observation_space != gym.make(f"TaskAlloc/{env}-EntityShift-v0").observation_space
        )
        ent = {r["method"]: r["mean"] for r in records if r["row"] == "zero-shot (entity)"}
        assert ent["Ours"] != "n/a" and ent["W/o Pre (random)"] != "n/a"
        assert all((ent[m] == "n/a") == resized for m in ("W/o TAM", "W/o AMIX", "MaskablePPO"))
        scratch = {r["method"]: r for r in records if r["row"].startswith("from scratch")}
        assert scratch["Ours"]["mean"] != "n/a" and scratch["Greedy"]["std"] == "static"
        assert scratch["W/o TAM"]["std"] == "scratch"
        assert re.search(r"Ours zero-shot / from scratch on the entity shift: (-?\d+\.\d+|n/a)", text), text
        assert len(list((smoke_tables / env / "models").glob("ours_s0_from_scratch*entity_*.zip"))) == 1
        assert (smoke_tables / env / "curves.png").stat().st_size > 0
    goal = r"Ours / best planner \((GA|PSO|SOS)\) on the training env: (-?\d+\.\d+|n/a)"
    assert re.search(goal, text)
    # The per-step MILP's gap, filed per cell and pooled under the table.
    gaps = json.loads((smoke_tables / env / "milp_gaps.json").read_text())
    assert any(key.startswith("train|0|") for key in gaps)  # row, seed and the cell's configuration
    assert all(g["solves"] > 0 and 0 <= g["stopped"] <= 1 for g in gaps.values())
    line = r"MILP: HiGHS with \{.*'node_limit': 5\} per solve; \d+% of \d+ solves stopped short of proven optimality"
    assert re.search(line, text)


def test_resume_computes_only_missing_cells(smoke_tables):
    cells = smoke_tables / "EPT" / "cells.csv"
    before = cells.read_text().splitlines()
    table_before = (smoke_tables / "EPT" / "table.md").read_text()
    run_smoke("EPT", smoke_tables)  # nothing missing: nothing recomputed
    assert cells.read_text().splitlines() == before
    assert (smoke_tables / "EPT" / "table.md").read_text() == table_before
    kept = [line for line in before if not line.startswith("Ours,few-shot (task)")]
    cells.write_text("\n".join(kept) + "\n")  # as if interrupted before that cell
    run_smoke("EPT", smoke_tables)
    after = cells.read_text().splitlines()
    assert after[: len(kept)] == kept and len(after) == len(kept) + 1 and after[-1].startswith("Ours,few-shot (task),0,")


def test_few_shot_cell_is_computed_again_identically(smoke_tables):
    """Fine-tuning after ``load`` is seeded: a few-shot cell computed again (its model and its line gone) in another
    process state gives the same value (it differed between identical runs)."""
    cells = smoke_tables / "EPT" / "cells.csv"
    before = cells.read_text().splitlines()
    line = next(line for line in before if line.startswith("Ours,few-shot (entity),0,"))
    from sb3_taskalloc import TwoStageSAC

    model = next((smoke_tables / "EPT" / "models").glob("ours_s0_few_shot__entity_*.zip"))
    first = TwoStageSAC.load(model).policy.state_dict()
    model.unlink()
    cells.write_text("\n".join(x for x in before if x != line) + "\n")
    import torch as th

    th.manual_seed(12345)  # another global random state than the fixture's process had
    run_smoke("EPT", smoke_tables)
    again = next(x for x in cells.read_text().splitlines() if x.startswith("Ours,few-shot (entity),0,"))
    assert again.split(",")[3] == line.split(",")[3]
    second = TwoStageSAC.load(model).policy.state_dict()
    assert all(th.equal(first[name], second[name]) for name in first)  # the same fine-tuning, not only the same score


def test_resume_after_a_row_cut_mid_line(smoke_tables):
    """A kill while a cell is appended leaves a partial last line: the resume drops it and recomputes that cell."""
    cells = smoke_tables / "EPT" / "cells.csv"
    lines = cells.read_text().splitlines()
    cells.write_text("\n".join(lines[:-1]) + "\n" + lines[-1][: len(lines[-1]) // 2])  # no trailing newline
    run_smoke("EPT", smoke_tables)
    after = cells.read_text().splitlines()
    assert after[:-1] == lines[:-1] and after[-1].split(",")[:3] == lines[-1].split(",")[:3]
