"""Learning check (slow): the paper's first experiment on "Retain the Almighty".

TwoStageSAC reaches the optimum 35 in deterministic evaluation in at least 4 of 5 seeds within the budget below
(measured: 35, 35, 35, 35, 33 for seeds 0–4; at 800 steps: 33, 35, 35, 35, 25).

The paper's contrast — sequential selection without pre-assignment getting stuck — did not reproduce with this
project's select stage: ``preassign=False, task_order="sequential"`` reached 35 in all 5 seeds at 800 steps. Its
pointer sees how much of each entity's supply a task would waste, and learns to spend specialists on single-skill
tasks, so it keeps the almighty entity for the last task. That comparison is therefore reported in the README, not
asserted here.
"""

from __future__ import annotations

import multiprocessing as mp
import os

import pytest

#: Env steps per seed (one-step episodes), learning rate and warm-up of the check.
BUDGET = {"total_timesteps": 1200, "learning_rate": 1e-3, "learning_starts": 200}
SEEDS = range(5)


def train_and_evaluate(args: tuple[int, dict]) -> float:
    seed, policy_kwargs = args
    os.environ["OMP_NUM_THREADS"] = "1"
    import gymnasium as gym
    import torch as th

    import envs  # noqa: F401
    from sb3_taskalloc import TwoStageSAC

    th.set_num_threads(1)
    model = TwoStageSAC(
        "TAMPolicy",
        "TaskAlloc/Almighty-v0",
        learning_rate=BUDGET["learning_rate"],
        learning_starts=BUDGET["learning_starts"],
        seed=seed,
        policy_kwargs=policy_kwargs,
    )
    model.learn(BUDGET["total_timesteps"])
    env = gym.make("TaskAlloc/Almighty-v0")
    obs, _ = env.reset(seed=seed)
    _, reward, terminated, _, _ = env.step(model.predict(obs, deterministic=True)[0])
    assert terminated
    return float(reward)


@pytest.mark.slow
def test_almighty_reaches_optimum():
    with mp.get_context("fork").Pool(2) as pool:
        returns = pool.map(train_and_evaluate, [(seed, {}) for seed in SEEDS], chunksize=1)
    print(f"\nAlmighty after {BUDGET['total_timesteps']} steps: {returns}")
    assert sum(r == pytest.approx(35.0) for r in returns) >= 4, returns
