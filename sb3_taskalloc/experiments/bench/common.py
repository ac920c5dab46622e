"""What the benchmarks share: devices, timing helpers and the states of seeded episodes (the machine's description:
:func:`sb3_taskalloc.experiments.evaluation.machine`)."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    pass


BenchFn = Callable[[argparse.Namespace], list[dict[str, Any]]]


def bench_devices(args: argparse.Namespace) -> list[str]:
    """The torch devices that ``--device`` names: ``auto`` is the CPU, plus CUDA when a GPU is available."""
    import torch as th

    from sb3_taskalloc.common.utils import cuda_unavailable

    if args.device == "auto":
        return ["cpu"] + (["cuda"] if th.cuda.is_available() else [])
    if why := cuda_unavailable(args.device):
        raise SystemExit(why)
    return [args.device]


def sync(device: str) -> None:
    """Wait for the device's queued work, so that a host clock times it (a no-op on the CPU)."""
    if device == "cuda":
        import torch as th

        th.cuda.synchronize()


def median_ms(fn: Callable[[], Any], reps: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def scaled_rbf(n_entities: int, n_tasks: int) -> Any:
    """An RBF env with ``n_entities`` entities (the training table repeated) and every one of ``n_tasks`` slots open."""
    from envs.rbf import RBFEnv

    return RBFEnv(entity_rows=[i % 100 for i in range(n_entities)], max_tasks=n_tasks, arrival_count=(n_tasks, n_tasks))


def episode_states(agent: Any, env_id: str, seeds: list[int], limit: int | None = None) -> list[dict[str, np.ndarray]]:
    """The observations of deterministic episodes of ``agent`` on ``env_id`` (the states a deployed policy meets).

    :param limit: the first ``limit`` states only (None: every state of every episode)
    """
    import gymnasium as gym

    states: list[dict[str, np.ndarray]] = []
    for seed in seeds:
        env = gym.make(env_id)
        obs, _ = env.reset(seed=seed)
        done = False
        while not done:
            if len(states) == limit:
                return states
            states.append(obs)
            obs, _, terminated, truncated, _ = env.step(agent.predict(obs, deterministic=True)[0])
            done = terminated or truncated
    return states


def state_latencies_ms(agent: Any, states: list[dict[str, np.ndarray]], device: str = "cpu") -> np.ndarray:
    """Wall time of one ``predict`` per state, in ms (after 3 warm-up calls)."""
    for obs in states[:3]:
        agent.predict(obs, deterministic=True)
    times = []
    for obs in states:
        t0 = time.perf_counter()
        agent.predict(obs, deterministic=True)
        sync(device)
        times.append(time.perf_counter() - t0)
    return np.asarray(times) * 1e3


def rbf_model(args: argparse.Namespace) -> tuple[Any, str]:
    """The trained model of the policy and labels benchmarks: ``--model``, or TwoStageSAC trained here on RBF for
    ``--train-steps`` at the defaults. :return: it and its source, in words"""
    import gymnasium as gym

    from sb3_taskalloc import TwoStageSAC

    if args.model:
        return TwoStageSAC.load(args.model, device="cpu"), args.model
    steps = args.train_steps or (100 if args.quick else 3000)
    model = TwoStageSAC("TAMPolicy", gym.make("TaskAlloc/RBF-v0"), seed=0, device="cpu")
    model.learn(steps)
    return model, f"trained here, {steps} steps at the defaults"
