"""Env throughput with random valid allocations, and the baselines' time per decision."""

from __future__ import annotations

import argparse
import copy
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    pass

from sb3_taskalloc.experiments.bench.common import scaled_rbf


def bench_envs(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Env steps/s with random valid allocations (one thread, unwrapped and as made by ``gym.make``) and deepcopy time.
    The rate is the fastest of five blocks, as ``timeit`` advises: the step's work is fixed, so a slower block measures
    other load on the machine, not the env (the blocks are in the record)."""
    import gymnasium as gym

    import envs
    from envs.rendering import random_valid_action

    targets = {"TaskAlloc/RBF-v0": 5000, "TaskAlloc/MT-v0": 5000, "TaskAlloc/EPT-v0": 10000}
    rows = []
    for env_id in envs.ENV_SPECS:
        if args.quick and env_id not in targets and "Almighty" not in env_id:
            continue
        result: dict[str, Any] = {"env": env_id}
        for label, wrapped in (("steps_per_s", False), ("steps_per_s_gym_make", True)):
            env: Any = gym.make(env_id) if wrapped else gym.make(env_id).unwrapped
            rng = np.random.default_rng(0)
            obs, _ = env.reset(seed=0)
            blocks = []
            for _ in range(5):
                n, t0 = 0, time.perf_counter()
                while time.perf_counter() - t0 < (0.1 if args.quick else 0.5):
                    obs, _, term, trunc, _ = env.step(random_valid_action(obs, rng))
                    n += 1
                    if term or trunc or (not wrapped and env._t >= envs.ENV_SPECS[env_id][2]):
                        obs, _ = env.reset()
                blocks.append(n / (time.perf_counter() - t0))
            result[label] = max(blocks)
            result[f"{label}_blocks"] = [round(b) for b in blocks]
        base: Any = gym.make(env_id).unwrapped
        obs, _ = base.reset(seed=0)
        for _ in range(10):
            obs, *_ = base.step(random_valid_action(obs, np.random.default_rng(1)))
        reps = 2000
        t0 = time.perf_counter()
        for _ in range(reps):
            copy.deepcopy(base)
        result["deepcopy_ms"] = (time.perf_counter() - t0) / reps * 1e3
        result["entities"] = base.n_entities
        result["target_steps_per_s"] = targets.get(env_id)
        rows.append(result)
    return rows


def bench_baselines(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Seconds per decision of every baseline and of TwoStageSAC on RBF (planners at the budget the experiments use
    and at the paper's settings), and MILP solve time against the instance size."""
    import gymnasium as gym
    import torch as th

    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.baselines import (
        GeneticAlgorithm,
        GreedyAllocator,
        MILPAllocator,
        ParticleSwarm,
        RecedingHorizonPlanner,
        SymbioticOrganismsSearch,
    )
    from sb3_taskalloc.experiments.budgets import MILP_NODE_LIMIT, PLANNER_BUDGET

    rows: list[dict[str, Any]] = []
    steps = 10 if args.quick else 30

    def per_decision(make: Callable[[Any], Any], n: int = steps) -> float:
        env = gym.make("TaskAlloc/RBF-v0")
        agent = make(env)
        obs, _ = env.reset(seed=0)
        t0 = time.perf_counter()
        for _ in range(n):
            obs, *_ = env.step(agent.predict(obs, deterministic=True)[0])
        return (time.perf_counter() - t0) / n

    th.manual_seed(0)
    sac = TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", seed=0, device="cpu")  # the baselines run on the CPU
    rows.append({"method": "TwoStageSAC (untrained)", "setting": "defaults", "s_per_decision": per_decision(lambda _: sac)})
    rows.append({"method": "Greedy", "setting": "", "s_per_decision": per_decision(lambda env: GreedyAllocator())})
    reference = f"the experiments' reference: {MILP_NODE_LIMIT} HiGHS nodes per solve, no clock"
    milp_per_decision = per_decision(lambda _: MILPAllocator.reference(MILP_NODE_LIMIT))
    rows.append({"method": "MILP", "setting": reference, "s_per_decision": milp_per_decision})
    planners: list[type[RecedingHorizonPlanner]] = [GeneticAlgorithm, ParticleSwarm, SymbioticOrganismsSearch]
    for cls in planners:

        def make_planner(env: Any, cls: type[RecedingHorizonPlanner] = cls) -> RecedingHorizonPlanner:
            return cls(env, seed=0, **PLANNER_BUDGET)

        used = per_decision(make_planner, n=20)  # two re-plans
        rows.append({"method": cls.__name__, "setting": f"experiments: {PLANNER_BUDGET}", "s_per_decision": used})
        # Paper settings (population 100, 1000 iterations): one iteration measured, then scaled; re-plan every 10 steps.
        env = gym.make("TaskAlloc/RBF-v0")
        env.reset(seed=0)
        planner = cls(env, seed=0, budget=100 * (1 + cls.rollouts_per_iteration))  # one iteration at population 100
        t0 = time.perf_counter()
        planner.plan()
        per_rollout = (time.perf_counter() - t0) / max(planner.last["rollouts"], 1)
        rollouts = 100 * (1 + 1000 * cls.rollouts_per_iteration)
        rows.append(
            {
                "method": cls.__name__,
                "setting": "paper (estimated: measured s/rollout × rollouts / 10 steps)",
                "s_per_decision": per_rollout * rollouts / 10,
            }
        )
    milp = MILPAllocator(time_limit=60.0)
    for n, m in [(20, 5), (50, 10), (100, 10)] if args.quick else [(20, 5), (50, 10), (100, 10), (200, 10), (500, 20)]:
        env = scaled_rbf(n, m)
        obs, _ = env.reset(seed=0)
        milp.allocate(obs)
        assert milp.last is not None
        rows.append(
            {
                "method": "MILP solve",
                "setting": f"{n} entities x {m} tasks ({milp.last.message}, gap {milp.last.mip_gap})",
                "s_per_decision": milp.last.seconds,
            }
        )
    return rows
