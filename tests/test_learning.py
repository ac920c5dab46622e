"""Learning checks: the paper's first experiment on "Retain the Almighty" (the full check is ``slow``, one seed of it is
not).

Within the budget below, TwoStageSAC reaches the optimum 35 in deterministic evaluation in at least 4 of 5 seeds, while
selection without pre-assignment in slot order (``preassign=False, task_order="sequential"``) does not in most seeds:
its single-skill tasks, decoded first, spend the almighty entity, and the all-skill task is then covered by eight
specialists (return 28). Measured at the defaults: pre-assignment 35 in 5 of 5 seeds at 400, 500, 600, 800 steps and
the zoo block's 1,200, in 4 of 5 at 350 (seed 4: 33) and in none at 300; sequence 28 in 3 of 3 seeds at 350, 400, 500
and 600 steps (2 of 3 at 800, 35 in seed 1). The check runs at 400, the shortest budget measured at 5 of 5, and asks 4
(it stops training seeds once the verdict is settled); the sequence variant on one seed.
"""

from __future__ import annotations

import pytest

#: Env steps per seed (one-step episodes), learning rate and warm-up of the check: the zoo block's settings at 400 of
#: its 1,200 steps, to fit CI.
BUDGET = {"total_timesteps": 400, "learning_rate": 1e-3, "learning_starts": 200}
SEEDS = range(5)
#: The sequence variant decodes its tasks one after the other (about 2× slower per step): to fit CI it is checked on
#: one seed, at the same budget (it fails if that seed reaches the optimum).
SEQUENCE_SEEDS, SEQUENCE_STEPS = range(1), BUDGET["total_timesteps"]


def train_and_evaluate(seed: int, policy_kwargs: dict, steps: int) -> float:
    import gymnasium as gym

    from sb3_taskalloc import TwoStageSAC

    model = TwoStageSAC(
        "TAMPolicy",
        "TaskAlloc/Almighty-v0",
        learning_rate=BUDGET["learning_rate"],
        learning_starts=BUDGET["learning_starts"],
        seed=seed,
        policy_kwargs=policy_kwargs,
    )
    model.learn(steps)
    env = gym.make("TaskAlloc/Almighty-v0")
    obs, _ = env.reset(seed=seed)
    _, reward, terminated, _, _ = env.step(model.predict(obs, deterministic=True)[0])
    assert terminated
    return float(reward)


#: Almighty's optimal return, and the pre-assign seeds that must reach it.
OPTIMUM, REQUIRED = 35.0, 4


def test_almighty_preassignment_reaches_optimum_on_one_seed():
    """``make test``'s learning check (the full one below is ``slow``: ``make test-slow``): seed 0 reaches the optimum
    within the budget, as every seed measured at it does; the same model untrained, or trained at learning rate 0,
    returns 2."""
    assert train_and_evaluate(0, {}, BUDGET["total_timesteps"]) == pytest.approx(OPTIMUM)


def reach_optimum(seeds: range, required: int) -> tuple[bool, list[float]]:
    """Whether at least ``required`` of ``seeds`` reach the optimum, and the returns trained for it: the seeds in order,
    stopping once the rest cannot change the verdict (four optimal seeds of five leave the fifth untrained)."""
    returns: list[float] = []
    for done, seed in enumerate(seeds, start=1):
        returns.append(train_and_evaluate(seed, {}, BUDGET["total_timesteps"]))
        optimal = sum(r == pytest.approx(OPTIMUM) for r in returns)
        if optimal >= required or optimal + len(seeds) - done < required:
            break
    return optimal >= required, returns


@pytest.mark.slow
def test_almighty_preassignment_reaches_optimum_and_sequence_gets_stuck():
    sequence = {"preassign": False, "task_order": "sequential"}
    # In this process, one training after the other: under pytest-xdist the other worker runs the rest of the suite
    # beside it (a pool of its own would start two more interpreters on CI's two cores).
    reached, returns = reach_optimum(SEEDS, REQUIRED)
    stuck = [train_and_evaluate(seed, sequence, SEQUENCE_STEPS) for seed in SEQUENCE_SEEDS]
    print(f"\nAlmighty after {BUDGET['total_timesteps']} steps: pre-assign {returns}, sequence {stuck}")
    assert reached, f"fewer than {REQUIRED} of {len(SEEDS)} seeds reach {OPTIMUM}: {returns}"
    assert not any(r == pytest.approx(OPTIMUM) for r in stuck), stuck  # does not reach the optimum
