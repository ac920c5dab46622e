"""The envs against the paper's published tables and reference data: Almighty's step values and optimum, the
generators' tables and the reference arrival schedules."""

from __future__ import annotations

import json

import numpy as np
import pytest

import envs
from envs.tables import DATA_DIR
from tests.test_envs import make


def alloc_to_action(alloc, n=25, m=9):
    action = np.full(n, m)
    for j, team in enumerate(alloc):
        action[team] = j
    return action


def test_almighty_reference_values():
    data = json.loads((DATA_DIR / "almighty.json").read_text())
    env = make("TaskAlloc/Almighty-v0")
    values = {}
    for name, expected in data["reference_step_values"].items():
        alloc = json.loads(name) if name.startswith("[") else None
        values[name] = expected
        if alloc is not None:
            env.reset(seed=0)
            _, r, term, _, _ = env.step(alloc_to_action(alloc))
            assert term and r == pytest.approx(expected), name
    # The described (non-literal) allocations.
    specialists = [[3 * k] for k in range(1, 8)]
    cases = {
        "almighty on task 0, task 8 empty": [[24], *specialists, []],
        "task 8 given only [1,4] (incomplete, not charged)": [[24], *specialists, [1, 4]],
    }
    for key, alloc in cases.items():
        env.reset(seed=0)
        _, r, _, _, _ = env.step(alloc_to_action(alloc))
        assert r == pytest.approx(data["reference_step_values"][key]), key
    env.reset(seed=0)
    _, r, _, _, _ = env.step(alloc_to_action(data["constants"]["optimal_allocation"]))
    assert r == data["constants"]["optimal_return"] == 35


def test_almighty_generator_matches_data():
    data = json.loads((DATA_DIR / "almighty.json").read_text())
    ents, tasks = envs.almighty_tables()
    np.testing.assert_array_equal(np.column_stack([ents.cost, ents.supply]), data["entities"])
    np.testing.assert_array_equal(tasks.rows, data["tasks"])
    small = envs.AlmightyEnv(n_skills=3, specialists=2)
    assert small.n_entities == 7 and small.max_tasks == 4


def test_mt_generator_matches_published_table():
    data = json.loads((DATA_DIR / "mt.json").read_text())
    np.testing.assert_array_equal(envs.generate_trucks(100, 0), data["entities_generated_seed0"])
    trucks = envs.generate_trucks(50, 0)
    np.testing.assert_array_equal(trucks[:, 1:4].sum(1), 5 * trucks[:, 0])


def test_reference_arrival_schedule():
    data = json.loads((DATA_DIR / "rbf.json").read_text())
    env = make("TaskAlloc/RBF-v0", arrival="reference", max_tasks=5)
    obs, _ = env.reset(seed=0)
    np.testing.assert_allclose(obs["task_reward"], np.asarray(data["tasks_train"])[:5, 0])
    np.testing.assert_allclose(obs["task_features"][:, 4:6], np.asarray(data["task_positions"])[:5])
    ept = make("TaskAlloc/EPT-v0", arrival="reference")
    seq = json.loads((DATA_DIR / "ept.json").read_text())["task_sequence"]
    ept.reset(seed=0)
    np.testing.assert_array_equal(ept._tower, seq[:5])
    obs, *_ = ept.step(np.full(ept.max_entities, ept.max_tasks))
    assert not obs["entity_mask"][seq[:5]].any(), "towers at peak demand cannot supply"
