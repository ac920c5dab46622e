"""The environment contract shared by every TaskAlloc env."""

from __future__ import annotations

import copy
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env

import envs
from envs.core import TaskAllocEnv
from envs.rendering import random_valid_action, save_gif

ENV_IDS = list(envs.ENV_SPECS)
RANDOM_IDS = [e for e in ENV_IDS if "Almighty" not in e]


def make(env_id: str, **kwargs) -> TaskAllocEnv:
    return gym.make(env_id, **kwargs).unwrapped  # type: ignore[return-value]


def rollout(env: gym.Env, seed: int, steps: int = 60, action_seed: int = 0):
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(action_seed)
    trace = [obs]
    rewards = []
    for _ in range(steps):
        obs, r, term, trunc, _ = env.step(random_valid_action(obs, rng))
        trace.append(obs)
        rewards.append(r)
        if term or trunc:
            break
    return trace, rewards


def same_trace(a, b) -> bool:
    return len(a) == len(b) and all(all(np.array_equal(x[k], y[k]) for k in x) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_check_env(env_id):
    # SB3's checker advises 1-D vectors for its default MLP policies; the 2-D (N, F) keys are the TaskAlloc layout
    # and are consumed by TAMPolicy. Every other warning is an error.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.filterwarnings("ignore", message=".*unconventional shape.*")
        check_env(make(env_id))
        gym_check_env(make(env_id))


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_observations_in_space_and_masks(env_id):
    env = make(env_id)
    trace, _ = rollout(env, seed=1, steps=150)
    for obs in trace:
        assert env.observation_space.contains(obs)
        M = env.max_tasks
        mask = obs["action_mask"].reshape(env.max_entities, M + 1)
        assert np.all(mask[:, M] == 1), "unassigned must always be valid"
        expected = obs["entity_mask"][:, None] & obs["task_mask"][None, :]
        np.testing.assert_array_equal(mask[:, :M], expected)
    np.testing.assert_array_equal(env.action_masks(), trace[-1]["action_mask"].astype(bool))


@pytest.mark.parametrize("env_id", RANDOM_IDS)
def test_seeding(env_id):
    a, ra = rollout(make(env_id), seed=3)
    b, rb = rollout(make(env_id), seed=3)
    c, _ = rollout(make(env_id), seed=4)
    assert same_trace(a, b) and ra == rb
    assert not same_trace(a, c)


class Tracker:
    """Independent bookkeeping of commitments, charges and completions from the observations alone."""

    def __init__(self, env: TaskAllocEnv):
        self.env = env
        self.task_of: dict[int, int] = {}
        self.charge: dict[int, float] = {}

    def step(self, obs, action):
        env = self.env
        M = env.max_tasks
        emask, tmask = obs["entity_mask"].astype(bool), obs["task_mask"].astype(bool)
        chosen = action < M
        valid = chosen & emask & np.append(tmask, False)[action]
        # A busy entity is never free.
        for i in self.task_of:
            assert not emask[i], f"committed entity {i} shown as free"
        new_obs, reward, term, trunc, info = env.step(action)
        assert info["invalid_assignments"] == int((chosen & ~valid).sum())
        if env.busy:
            for i in np.flatnonzero(valid):
                self.task_of[int(i)] = int(action[i])
                self.charge[int(i)] = float(obs["pair_cost"][i, action[i]])
            released = [i for i in self.task_of if new_obs["entity_mask"][i] or not new_obs["entity_supply"][i].any()]
            slots = {self.task_of[i] for i in released}
            expected_cost = sum(self.charge[i] for i in released)
            expected_reward = sum(float(obs["task_reward"][j]) for j in slots)
            for i in released:
                del self.task_of[i], self.charge[i]
        else:
            slots = set()
            expected_cost = 0.0
            for j in range(M):
                team = np.flatnonzero(valid & (action == j))
                if len(team) and np.all(obs["entity_supply"][team].sum(0) >= obs["task_demand"][j] - 1e-4):
                    slots.add(j)
                    expected_cost += float(obs["pair_cost"][team, j].sum())
            expected_reward = sum(float(obs["task_reward"][j]) for j in slots)
        assert info["completed_tasks"] == len(slots)
        assert info["cost_total"] == pytest.approx(expected_cost, rel=1e-4, abs=1e-4)
        assert info["task_reward_total"] == pytest.approx(expected_reward, rel=1e-4, abs=1e-4)
        assert reward == pytest.approx(expected_reward - expected_cost, rel=1e-4, abs=1e-4)
        # Resources are never created.
        assert new_obs["entity_supply"].sum() <= obs["entity_supply"].sum() + 1e-3
        return new_obs, term or trunc


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_random_actions_keep_invariants(env_id):
    env = make(env_id)
    rng = np.random.default_rng(0)
    for episode in range(2):
        obs, _ = env.reset(seed=episode)
        tracker = Tracker(env)
        for _ in range(200):
            # Half arbitrary in-space actions (mask violations included), half valid allocations.
            action = env.action_space.sample() if rng.random() < 0.5 else random_valid_action(obs, rng)
            obs, done = tracker.step(obs, action)
            if done:
                break


@pytest.mark.parametrize(
    "action, match",
    [
        (np.zeros(7, dtype=np.int64), "shape"),
        (np.full(100, -1), r"\[0, 10\]"),
        (np.full(100, 11), r"\[0, 10\]"),
        (np.full(100, np.nan), "NaN"),
        (np.full(100, 0.5), "non-integer"),
        (np.array(["a"] * 100), "dtype"),
        (np.full((2, 50), 10), r"shape \(100,\)"),  # the right size in the wrong shape is not reshaped
        (np.ones(100, dtype=bool), "dtype bool"),
    ],
)
def test_out_of_space_actions_raise(action, match):
    env = make("TaskAlloc/RBF-v0")
    env.reset(seed=0)
    with pytest.raises(ValueError, match=match):
        env.step(action)


def test_strict_mask_violation_raises():
    env = make("TaskAlloc/RBF-v0", strict=True, max_tasks=12)
    obs, _ = env.reset(seed=0)
    closed = np.flatnonzero(obs["task_mask"] == 0)
    assert len(closed), "RBF starts with free slots"
    with pytest.raises(ValueError, match="violate the action mask"):
        env.step(np.full(env.max_entities, closed[0]))


def test_lenient_mask_violation_counts():
    env = make("TaskAlloc/RBF-v0", max_tasks=12)
    obs, _ = env.reset(seed=0)
    closed = np.flatnonzero(obs["task_mask"] == 0)[0]
    _, reward, _, _, info = env.step(np.full(env.max_entities, closed))
    assert info["invalid_assignments"] == env.n_entities and reward == 0.0


@pytest.mark.parametrize("env_id", ["TaskAlloc/RBF-v0", "TaskAlloc/MT-v0", "TaskAlloc/EPT-v0"])
def test_deepcopy_continues_identically(env_id):
    env = make(env_id)
    obs, _ = env.reset(seed=5)
    rng = np.random.default_rng(1)
    for _ in range(7):
        obs, *_ = env.step(random_valid_action(obs, rng))
    clone = copy.deepcopy(env)
    for _ in range(30):
        action = random_valid_action(obs, rng)
        o1, r1, t1, _, _ = env.step(action)
        o2, r2, t2, _, _ = clone.step(action)
        assert r1 == r2 and t1 == t2
        assert all(np.array_equal(o1[k], o2[k]) for k in o1)
        obs = o1
    # The clone does not share mutable state.
    clone.step(random_valid_action(obs, rng))
    assert clone.render_snapshot().t == env.render_snapshot().t + 1


def test_random_arrival_counts():
    env = make("TaskAlloc/RBF-v0", max_tasks=20)
    for seed in range(5):
        obs, _ = env.reset(seed=seed)
        assert 5 <= obs["task_mask"].sum() <= 10


def test_mt_trucks_are_used_up():
    env = make("TaskAlloc/MT-v0")
    obs, _ = env.reset(seed=0)
    rng = np.random.default_rng(0)
    used = np.zeros(env.max_entities, dtype=bool)
    for _ in range(150):
        obs, _, term, trunc, info = env.step(random_valid_action(obs, rng))
        used |= info["entity_income"] > 0
        assert not obs["entity_mask"][used].any() and not obs["entity_supply"][used].any()
        if term or trunc:
            break
    assert used.any()


def test_bidding_charges_bids():
    env = make("TaskAlloc/RBF-v0", bidding=True, travel_cost=0.0)
    obs, _ = env.reset(seed=0)
    bids = np.linspace(0.1, 1.0, env.n_entities)
    env.set_bids(bids)
    obs = env.observe()
    open_ = obs["task_mask"].astype(bool)
    np.testing.assert_allclose(obs["pair_cost"][:, open_], np.repeat(bids[:, None], open_.sum(), 1), rtol=1e-6)
    np.testing.assert_allclose(obs["entity_features"][:, -1], bids, rtol=1e-6)
    with pytest.raises(ValueError, match="bid_max"):
        env.set_bids(np.full(env.n_entities, 1e9))
    with pytest.raises(ValueError, match="shape"):
        env.set_bids(np.ones(3))
    with pytest.raises(RuntimeError, match="bidding=True"):
        make("TaskAlloc/RBF-v0").set_bids(bids)


def test_padding_masks_extra_entities():
    env = make("TaskAlloc/RBF-v0", max_entities=130)
    obs, _ = env.reset(seed=0)
    assert obs["entity_features"].shape == (130, 8)
    assert not obs["entity_mask"][100:].any() and not obs["entity_features"][100:].any()
    with pytest.raises(ValueError, match="max_entities"):
        make("TaskAlloc/RBF-v0", max_entities=10)


@pytest.mark.parametrize("env_id", ["TaskAlloc/RBF-v0", "TaskAlloc/EPT-v0", "TaskAlloc/Almighty-v0"])
def test_render(env_id, tmp_path):
    env = gym.make(env_id, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (400, 400, 3) and frame.dtype == np.uint8 and frame.min() < 255
    text = gym.make(env_id, render_mode="ansi")
    text.reset(seed=0)
    assert "tasks" in text.render()
    path, ret = save_gif(gym.make(env_id, render_mode="rgb_array"), None, tmp_path / "ep.gif", max_steps=5)
    assert path.stat().st_size > 0 and np.isfinite(ret)


def test_bad_constructor_arguments():
    with pytest.raises(ValueError, match="towers"):
        envs.EPTEnv(towers="nope")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="arrival"):
        envs.RBFEnv(arrival="sometimes")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="decay"):
        envs.RBFEnv(decay=1.5)
    with pytest.raises(RuntimeError, match="reset"):
        envs.RBFEnv().step(np.zeros(100, dtype=np.int64))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"reward_scale": 0}, r"reward_scale must lie in \(0.0, inf\)"),
        ({"travel_cost": -1}, r"travel_cost must lie in \[0.0, inf\)"),
        ({"grid_size": -5}, "grid_size must lie in"),
        ({"arrival_period": 0}, "arrival_period must lie in"),
        ({"demand_noise": 1.5}, "demand_noise must lie in"),
        ({"decay_after": -1}, "decay_after must lie in"),
        ({"bid_max": 0.0}, "bid_max must lie in"),
        ({"max_tasks": 0}, "max_tasks must lie in"),
        ({"travel": "teleport"}, "travel must be one of"),
    ],
)
def test_degenerate_settings_are_named(kwargs, match):
    """Settings that would build an env with tasks that never open, observations outside the space or a division by
    zero on the first step are refused when the env is built."""
    with pytest.raises(ValueError, match=match):
        make("TaskAlloc/RBF-v0", **kwargs)


def test_degenerate_tables_are_named():
    from envs import EntityTable, TaskAllocEnv, TaskTable

    ents = EntityTable(cost=[1.0, 1.0], supply=[[1.0], [2.0]])
    tasks = TaskTable(rows=[[3.0, 1.0]])
    TaskAllocEnv(ents, tasks, max_tasks=1).reset(seed=0)  # the valid reference
    cases = [
        (lambda: TaskTable(rows=[[-3.0, 1.0]]), "task rewards must be finite and > 0"),
        (lambda: TaskTable(rows=[[3.0, 0.0]]), "demand nothing"),
        (lambda: TaskTable(rows=np.zeros((0, 2))), "task table is empty"),
        (lambda: EntityTable(cost=[1.0], supply=[[-1.0]]), "entity supplies must be finite and >= 0"),
        (lambda: EntityTable(cost=[np.nan], supply=[[1.0]]), "entity costs must be finite"),
        (lambda: EntityTable(cost=[], supply=np.zeros((0, 1))), "entity table is empty"),
        (lambda: TaskAllocEnv(EntityTable([1.0], [[1.0]], positions=[[9, 0]]), tasks, grid_size=3), "on the grid"),
        # a column shorter than the table was zero-padded (entities at (0, 0), free wires)
        (lambda: EntityTable([1.0, 1.0], [[1.0], [1.0]], positions=[[1, 1]]), r"positions must have one row per entity \(2\)"),
        (lambda: EntityTable([1.0, 1.0], [[1.0], [1.0]], wire_cost=[1.0]), r"wire_cost must have one row per entity \(2\)"),
        (lambda: TaskTable(rows=[[3.0, 1.0], [3.0, 1.0]], positions=[[1, 1]]), "task positions must have one row per task"),
    ]
    for build, match in cases:
        with pytest.raises(ValueError, match=match):
            build()


def test_action_masks_before_reset_is_named():
    env = make("TaskAlloc/RBF-v0").unwrapped
    with pytest.raises(RuntimeError, match=r"call reset\(\) before action_masks"):
        env.action_masks()


def test_save_gif_takes_models_and_allocators(tmp_path):
    """Anything with SB3's ``predict`` drives the episode (run deterministically); other objects are named."""
    from sb3_taskalloc.baselines import GreedyAllocator

    env = gym.make("TaskAlloc/EPT-v0", render_mode="rgb_array")
    _, greedy_return = save_gif(env, GreedyAllocator(), tmp_path / "greedy.gif", seed=3, max_steps=4)
    _, fn_return = save_gif(env, lambda o: GreedyAllocator().predict(o)[0], tmp_path / "fn.gif", seed=3, max_steps=4)
    assert greedy_return == fn_return and (tmp_path / "greedy.gif").stat().st_size > 0
    with pytest.raises(TypeError, match="have predict"):
        save_gif(env, 42, tmp_path / "x.gif")


@pytest.mark.parametrize("while_committed", [True, False])
def test_decay_of_committed_tasks(while_committed):
    """With ``decay_while_committed=False`` (MT's default) a task that a truck is driving to keeps its reward; a task
    nobody serves keeps decaying either way."""
    from envs import EntityTable, TaskAllocEnv, TaskTable

    ents = EntityTable(cost=[1.0, 1.0], supply=[[1.0], [1.0]], positions=[[0, 0], [0, 0]])
    tasks = TaskTable(rows=[[8.0, 1.0], [8.0, 1.0]], positions=[[9, 9], [9, 9]])
    env = TaskAllocEnv(
        ents, tasks, max_tasks=2, grid_size=10, travel="chebyshev", arrival="static", decay=0.5, decay_after=0,
        decay_while_committed=while_committed,
    )  # fmt: skip
    obs, _ = env.reset(seed=0)
    for _ in range(3):
        obs, *_ = env.step(np.array([0, 2]) if obs["entity_mask"][0] else np.array([2, 2]))
    assert obs["task_reward"][1] == pytest.approx(8.0 * 0.5**3)  # nobody serves task 1
    assert obs["task_reward"][0] == pytest.approx(8.0 * 0.5**3 if while_committed else 8.0)
    assert gym.make("TaskAlloc/MT-v0").unwrapped.decay_while_committed is False


def test_commitment_reward_credits_at_closing_and_corrects_at_completion():
    """``info["commitment_reward"]`` pays reward − charges in the step the committed team covers the task, then the
    decay during travel when the team arrives: the same total as the env reward, steps earlier."""
    from envs import EntityTable, TaskAllocEnv, TaskTable

    ents = EntityTable(cost=[1.0, 1.0], supply=[[1.0], [1.0]], positions=[[0, 0], [0, 0]])
    tasks = TaskTable(rows=[[8.0, 2.0]], positions=[[3, 0]])
    env = TaskAllocEnv(
        ents, tasks, max_tasks=1, grid_size=10, travel="chebyshev", travel_cost=0.0, arrival="static", decay=0.9,
        decay_after=0,
    )  # fmt: skip
    env.reset(seed=0)
    _, r, *_, info = env.step(np.array([0, 1]))  # one entity: the task stays open
    assert (r, info["commitment_reward"]) == (0.0, 0.0)
    _, r, *_, info = env.step(np.array([1, 0]))  # the second entity closes it: credited now, before anyone arrives
    assert r == 0.0
    assert info["commitment_reward"] == pytest.approx(8.0 * 0.9**2 - 2.0)  # the reward after two steps of decay
    credits, paid = [info["commitment_reward"]], 0.0
    for _ in range(6):
        _, r, *_, info = env.step(np.array([1, 1]))
        credits.append(info["commitment_reward"])
        paid += r
        if r:
            break
    assert paid != 0.0 and sum(credits) == pytest.approx(paid)  # the decay during travel is corrected on arrival


@pytest.mark.parametrize("env_id", ["TaskAlloc/RBF-v0", "TaskAlloc/MT-v0", "TaskAlloc/EPT-v0", "TaskAlloc/Almighty-v0"])
def test_commitment_reward_sums_to_the_return(env_id):
    """Over an episode the commitment rewards sum to the return, less the credits of tasks still unpaid at truncation."""
    from sb3_taskalloc.baselines import GreedyAllocator

    env = gym.make(env_id)
    obs, _ = env.reset(seed=3)
    greedy = GreedyAllocator()
    paid = credited = 0.0
    done = early = False
    for _ in range(400):
        obs, r, terminated, truncated, info = env.step(greedy.predict(obs)[0])
        paid, credited = paid + r, credited + info["commitment_reward"]
        early |= credited != pytest.approx(paid)
        if terminated or truncated:
            done = True
            break
    assert done
    unpaid = 0.0 if terminated else float(env.unwrapped._credit.sum())
    assert credited - unpaid == pytest.approx(paid, abs=1e-6)
    assert early or env_id in ("TaskAlloc/EPT-v0", "TaskAlloc/Almighty-v0")  # with travel the credit comes first


@pytest.mark.parametrize("bidding", [False, True])
def test_ept_tower_tables_equal_the_pair_cost_formula(bidding):
    """EPT's pair costs and distances come from tables computed once (its towers never move); at every step they
    equal, to the bit, what the general formula computes from the slots' cells, empty slots included."""
    from envs.geometry import distances, pair_costs

    env = make("TaskAlloc/EPT-v0", bidding=bidding)
    assert env._tower_tables is not None and make("TaskAlloc/RBF-v0")._tower_tables is None
    obs, _ = env.reset(seed=1)
    rng = np.random.default_rng(0)
    empty_seen = 0
    for _ in range(80):
        if bidding:
            env.set_bids(rng.uniform(0.0, env.bid_max, env.n_entities))
            obs = env.observe()
        dist = distances(env._pos, env._tpos, env.travel)
        base = env._bid if bidding else env._cost0
        np.testing.assert_array_equal(env._dist, dist)
        np.testing.assert_array_equal(env._pc, pair_costs(base, dist, env.travel_cost, env._wire, env._tower))
        empty_seen += int((env._tower < 0).sum())
        obs, *_ = env.step(random_valid_action(obs, rng))
    assert empty_seen > 0  # the empty slots' column was checked too


def test_an_env_pickled_before_the_step_tables_steps_on():
    """A training checkpoint pickles its envs; one written before the EPT tables and the entity-features flag existed
    unpickles without them and steps exactly as the env it was."""
    import pickle

    env = make("TaskAlloc/EPT-v0")
    obs, _ = env.reset(seed=2)
    for _ in range(5):
        obs, *_ = env.step(random_valid_action(obs, np.random.default_rng(5)))
    state = env.__dict__.copy()
    old = copy.copy(env)
    old.__dict__ = {k: v for k, v in state.items() if k not in ("_tower_tables", "_entities_dirty")}
    old = pickle.loads(pickle.dumps(old))
    assert "_tower_tables" not in old.__dict__
    traces = []
    for e in (env, old):
        rng = np.random.default_rng(7)
        o, trace, rewards = obs, [], []
        for _ in range(30):
            o, r, *_ = e.step(random_valid_action(o, rng))
            trace.append(o)
            rewards.append(r)
        traces.append((trace, rewards))
    assert same_trace(traces[0][0], traces[1][0]) and traces[0][1] == traces[1][1]
