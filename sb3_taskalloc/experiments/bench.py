"""Benchmarks: ``python -m sb3_taskalloc.bench {envs,policy,train,baselines,learn,labels,all} [--out DIR]``.

Each benchmark prints a table and writes ``<out>/bench_<name>.json`` with the figures, the machine and the command.
Figures are measured with one thread (``OMP_NUM_THREADS=1``, ``torch.set_num_threads(1)``) unless stated.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import shlex
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np

if TYPE_CHECKING:
    from sb3_taskalloc import TwoStageSAC

BenchFn = Callable[[argparse.Namespace], list[dict[str, Any]]]
#: The profiler's names of the host calls that launch a CUDA kernel.
LAUNCH_EVENTS = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx")
#: ``bench learn`` trains until the policy returns this multiple of its untrained initialisation.
LEARN_TARGET = 1.05


def _machine() -> dict[str, Any]:
    import torch as th

    return {
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "numpy": np.__version__,
        "torch": th.__version__,
        "gpu": th.cuda.get_device_name() if th.cuda.is_available() else None,
    }


def _devices(args: argparse.Namespace) -> list[str]:
    """The torch devices that ``--device`` names: ``auto`` is the CPU, plus CUDA when a GPU is available."""
    import torch as th

    from sb3_taskalloc.common.utils import cuda_unavailable

    if args.device == "auto":
        return ["cpu"] + (["cuda"] if th.cuda.is_available() else [])
    if why := cuda_unavailable(args.device):
        raise SystemExit(why)
    return [args.device]


def _sync(device: str) -> None:
    """Wait for the device's queued work, so that a host clock times it (a no-op on the CPU)."""
    if device == "cuda":
        import torch as th

        th.cuda.synchronize()


def bench_envs(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Env steps/s with random valid allocations (one thread, unwrapped and as made by ``gym.make``) and deepcopy time."""
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
            n, t0 = 0, time.perf_counter()
            budget = 0.5 if args.quick else 2.0
            while time.perf_counter() - t0 < budget:
                obs, _, term, trunc, _ = env.step(random_valid_action(obs, rng))
                n += 1
                if term or trunc or (not wrapped and env._t >= envs.ENV_SPECS[env_id][2]):
                    obs, _ = env.reset()
            result[label] = n / (time.perf_counter() - t0)
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


def _median_ms(fn: Callable[[], Any], reps: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def _scaled_rbf(n_entities: int, n_tasks: int) -> Any:
    """An RBF env with ``n_entities`` entities (the training table repeated) and every one of ``n_tasks`` slots open."""
    from envs.rbf import RBFEnv

    return RBFEnv(entity_rows=[i % 100 for i in range(n_entities)], max_tasks=n_tasks, arrival_count=(n_tasks, n_tasks))


def _episode_states(agent: Any, env_id: str, seeds: list[int]) -> list[dict[str, np.ndarray]]:
    """The observations of deterministic episodes of ``agent`` on ``env_id`` (the states a deployed policy meets)."""
    import gymnasium as gym

    states = []
    for seed in seeds:
        env = gym.make(env_id)
        obs, _ = env.reset(seed=seed)
        done = False
        while not done:
            states.append(obs)
            obs, _, terminated, truncated, _ = env.step(agent.predict(obs, deterministic=True)[0])
            done = terminated or truncated
    return states


def _state_latencies_ms(agent: Any, states: list[dict[str, np.ndarray]], device: str = "cpu") -> np.ndarray:
    """Wall time of one ``predict`` per state, in ms (after 3 warm-up calls)."""
    for obs in states[:3]:
        agent.predict(obs, deterministic=True)
    times = []
    for obs in states:
        t0 = time.perf_counter()
        agent.predict(obs, deterministic=True)
        _sync(device)
        times.append(time.perf_counter() - t0)
    return np.asarray(times) * 1e3


#: Pre-assignments of the decision-time search row (the ``preassign_search`` decoder; implementation detail 16).
SEARCH = 32
#: Teams per task of the decision-time team search row (the ``team_search`` decoder; implementation detail 20).
TEAM_SEARCH = 64
#: The trained policy's rows: its decoding strategies by name (:mod:`~sb3_taskalloc.two_stage_sac.decoding`) with
#: their settings, and the words they add to the row's name.
DECODER_ROWS: tuple[tuple[str, dict[str, Any], str], ...] = (
    ("argmax", {}, ""),
    ("preassign_search", {"samples": SEARCH}, f", search of {SEARCH}"),
    ("team_search", {"samples": TEAM_SEARCH}, f", team search of {TEAM_SEARCH}"),
    ("exact_covers", {}, ", exact covers"),
    ("exact_top", {"top": 1}, ", exact pre-assignment among each entity's top task"),
)


def _rbf_model(args: argparse.Namespace) -> tuple[Any, str]:
    """The trained model of the policy and labels benchmarks: ``--model``, or TwoStageSAC trained here on RBF for
    ``--train-steps`` at the defaults. :return: it and its source, in words"""
    import gymnasium as gym

    import envs  # noqa: F401
    from sb3_taskalloc import TwoStageSAC

    if args.model:
        return TwoStageSAC.load(args.model, device="cpu"), args.model
    steps = args.train_steps or (100 if args.quick else 3000)
    model = TwoStageSAC("TAMPolicy", gym.make("TaskAlloc/RBF-v0"), seed=0, device="cpu")
    model.learn(steps)
    return model, f"trained here, {steps} steps at the defaults"


def bench_policy_episodes(args: argparse.Namespace, devices: list[str]) -> list[dict[str, Any]]:
    """Decision latency over the states of seeded RBF episodes (median and p90) of a trained model (``--model``, or
    TwoStageSAC trained here for ``--train-steps`` at the defaults) and of the same policy untrained, with Greedy for
    reference: a reset state has more free entities and fewer open tasks than the states of an episode."""
    import gymnasium as gym
    import torch as th

    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.baselines import GreedyAllocator

    env_id = "TaskAlloc/RBF-v0"
    seeds = [30_000] if args.quick else [30_000, 30_001, 30_002]
    trained, source = _rbf_model(args)
    th.manual_seed(0)
    untrained = TwoStageSAC("TAMPolicy", gym.make(env_id), seed=0, device="cpu")
    states = _episode_states(trained, env_id, seeds)
    rows = []
    for device in devices:
        searched = [("trained", trained, *row) for row in DECODER_ROWS]
        for name, agent, decoder, config, words in [searched[0], ("untrained", untrained, "argmax", {}, ""), *searched[1:]]:
            agent.policy.to(device)
            agent.device = th.device(device)
            with agent.decoding(decoder, **config):
                ms = _state_latencies_ms(agent, states, device)
            rows.append(
                {"device": device, "policy": f"TAMPolicy {name}{words}", "decoder": decoder,
                 "states": len(states), "median_ms": float(np.median(ms)), "p90_ms": float(np.percentile(ms, 90)),
                 "model": source if name == "trained" else None,
                 "target": "median <= 5 ms, p90 <= 10 ms (CPU)" if decoder == "argmax" else None}
            )  # fmt: skip
    ms = _state_latencies_ms(GreedyAllocator(), states)
    rows.append({"device": "cpu", "policy": "Greedy", "states": len(states), "median_ms": float(np.median(ms)),
                 "p90_ms": float(np.percentile(ms, 90))})  # fmt: skip
    return rows


def bench_labels(args: argparse.Namespace) -> list[dict[str, Any]]:
    """The exact covers that label the pointer's DAgger (:meth:`~sb3_taskalloc.TwoStageSAC.distill_select`): every
    pre-assign round of seeded RBF episodes of a trained model's deterministic policy (``--model``), covered task by
    task (branch and bound, :func:`~sb3_taskalloc.baselines.milp.max_profit_team`) and by one HiGHS solve per round
    (the per-step MILP's formulation on the candidate pairs): seconds per round of each, and the largest difference
    between the two covers' profits (both exact: 0 up to the solvers' tolerances)."""
    import torch as th

    from sb3_taskalloc.two_stage_sac.search import exact_covers

    model, source = _rbf_model(args)
    policy = model.policy
    rounds: list[tuple[Any, th.Tensor]] = []
    for obs in _episode_states(model, "TaskAlloc/RBF-v0", [30_000] if args.quick else [30_000, 30_001, 30_002]):
        with th.inference_mode():
            policy.decide(policy.parse(policy.obs_to_tensor(obs)[0]), deterministic=True, rounds_out=rounds)
    M = rounds[0][0].task_mask.shape[1]
    tasks = sum(int((t.unsqueeze(-1) == th.arange(M)).any(1).sum()) for _, t in rounds)
    rows: list[dict[str, Any]] = []
    profits = []
    for by_task, name in ((True, "task by task (branch and bound)"), (False, "one HiGHS solve per round")):
        seconds, profit = 0.0, []
        for view, task_of in rounds:
            allowed = task_of.unsqueeze(-1) == th.arange(M)
            t0 = time.perf_counter()
            members = exact_covers(view, allowed, by_task=by_task)
            seconds += time.perf_counter() - t0
            team = (members.unsqueeze(-1) == th.arange(M)).double()  # (B, N, M)
            kept = team.any(1)
            profit.append((view.reward.double() * kept - (view.pair_cost.double() * team).sum(1)).sum(-1))
        profits.append(th.cat(profit))
        rows.append({"labeller": name, "rounds": len(rounds), "tasks": tasks,
                     "ms_per_round": seconds / len(rounds) * 1e3, "seconds": seconds, "model": source})  # fmt: skip
    rows[0]["speedup"] = rows[1]["seconds"] / rows[0]["seconds"]
    rows[0]["max_profit_difference"] = float((profits[0] - profits[1]).abs().max())
    return rows


def bench_policy(args: argparse.Namespace) -> list[dict[str, Any]]:
    """TAMPolicy decision latency: over the states of seeded RBF episodes (:func:`bench_policy_episodes`), then on one
    reset RBF observation, a batch of 256, and the N × M scaling table of reset states (CPU; CUDA when available)."""
    import torch as th
    from stable_baselines3.common.utils import obs_as_tensor

    from sb3_taskalloc import TAMPolicy

    devices = _devices(args)
    rows: list[dict[str, Any]] = bench_policy_episodes(args, devices)
    sizes = [(100, 10)] + [(n, m) for n in (50, 100, 500, 1000) for m in (5, 10, 50)]
    if args.quick:
        sizes = [(100, 10), (50, 5)]
    for device in devices:
        for i, (n, m) in enumerate(sizes):
            env = _scaled_rbf(n, m)
            obs, _ = env.reset(seed=0)
            th.manual_seed(0)
            policy = TAMPolicy(env.observation_space, env.action_space, lambda _: 3e-4).to(device)  # type: ignore[arg-type]
            policy.set_training_mode(False)
            reps = 5 if (args.quick or n * m >= 50_000) else 30
            row: dict[str, Any] = {"device": device, "entities": n, "tasks": m}
            row["predict_ms"] = _median_ms(lambda: policy.predict(obs, deterministic=True), reps)  # noqa: B023
            if i == 0:
                batch = obs_as_tensor({k: np.repeat(v[None], 256, 0) for k, v in obs.items()}, th.device(device))

                def decide_batch(policy: TAMPolicy = policy, batch: Any = batch, device: str = device) -> None:
                    with th.no_grad():
                        policy.decide(policy.parse(batch), deterministic=True)
                        _sync(device)

                row["batch256_ms_per_obs"] = _median_ms(decide_batch, 3 if args.quick else 10, warmup=1) / 256
                row["target"] = "predict <= 5 ms, batch 256 <= 0.5 ms/obs"
            rows.append(row)
    return rows


def bench_train(args: argparse.Namespace) -> list[dict[str, Any]]:
    """TwoStageSAC training throughput: env steps/s with one gradient step (batch 64) per collection step (the median of
    three blocks of ``learn``, each block recorded; one env, and on RBF also ``n_envs=8``, where one step collects 8
    transitions with one batched decision) and the minutes that rate needs for 100,000 env steps; the gradient step
    and the stochastic decision timed apart; replay memory; and the gradient step on RBF scaled to fewer entities (what
    a step costs apart from the entity count). On CUDA, also the GPU kernel time and the kernel launches per gradient
    step (``torch.profiler``; ``None`` on the CPU)."""
    import gymnasium as gym
    from stable_baselines3.common.env_util import make_vec_env

    import envs  # noqa: F401
    from sb3_taskalloc import TwoStageSAC

    def measure(model: TwoStageSAC, device: str, steps: int, env: str, target: int | None = None) -> dict[str, Any]:
        """One row: env steps/s of ``learn`` (the median of ``blocks`` runs of ``steps`` steps), then the gradient step
        and the stochastic decision timed apart (medians over single steps)."""
        model.learn(64)
        rates = []
        for _ in range(blocks):
            t0 = time.perf_counter()
            model.learn(steps, reset_num_timesteps=False)
            rates.append(steps / (time.perf_counter() - t0))
        rate = float(np.median(rates))
        reps = max(steps // 5, 4)

        def gradient_step() -> None:
            model.train(gradient_steps=1, batch_size=64)
            _sync(device)

        def decision() -> None:
            model._sample_action(learning_starts=0)
            _sync(device)

        grad_ms = _median_ms(gradient_step, reps, warmup=1)  # the warm-up step also waits for learn()'s queued work
        decision_ms = _median_ms(decision, reps, warmup=1)
        amix_ms = _amix_ms(model, device, reps)
        kernel_ms = launches = None
        if device == "cuda":  # how much of the gradient step the GPU computes, apart from the host's dispatch
            from torch.profiler import ProfilerActivity, profile

            with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
                model.train(gradient_steps=reps, batch_size=64)
                _sync(device)
            events = prof.key_averages()
            kernel_ms = sum(e.self_device_time_total for e in events if e.device_type.name == "CUDA") / reps / 1e3
            launches = sum(e.count for e in events if e.key in LAUNCH_EVENTS) / reps
        return {
            "device": device,
            "env": env,
            "env_steps_per_s": rate,
            "env_steps_per_s_blocks": [round(r, 2) for r in rates],
            "minutes_to_100k_steps": 1e5 / rate / 60,  # extrapolated from the rate, for RBF's paper budget
            "gradient_step_ms": grad_ms,
            "gpu_kernel_ms_per_gradient_step": kernel_ms,
            "kernel_launches_per_gradient_step": launches,
            "decision_ms": decision_ms,
            "amix_ms_per_gradient_step": amix_ms,
            # What the decision and AMIX's attention alone would allow, with everything else in a step free.
            "env_steps_per_s_bound": 1e3 / (decision_ms + amix_ms),
            "replay_GB_for_100k": model.replay_buffer.nbytes_per_transition() * 100_000 / 1e9,
            "target_steps_per_s": target,
        }

    devices = _devices(args)
    rows = []
    steps = 20 if args.quick else 100
    blocks = 1 if args.quick else 3  # the median of three blocks damps the run-to-run spread of one block
    for device in devices:
        for env_id in ("TaskAlloc/RBF-v0", "TaskAlloc/EPT-v0", "TaskAlloc/MT-v0", "TaskAlloc/Almighty-v0"):
            if args.quick and env_id != "TaskAlloc/RBF-v0":
                continue
            model = TwoStageSAC("TAMPolicy", gym.make(env_id), learning_starts=64, batch_size=64, seed=0, device=device)
            rows.append(measure(model, device, steps, env_id, 60 if env_id == "TaskAlloc/RBF-v0" else None))
            if env_id == "TaskAlloc/RBF-v0":  # vectorised collection: one batched decision for n_envs envs
                for n_envs in () if args.quick else (8,):
                    vec = make_vec_env(env_id, n_envs=n_envs, seed=0)
                    model = TwoStageSAC("TAMPolicy", vec, learning_starts=64, batch_size=64, seed=0, device=device)
                    rows.append(measure(model, device, steps * n_envs // 2, f"{env_id}, n_envs={n_envs}", 60))
        for n in () if args.quick else (10, 25, 50):
            env = gym.make("TaskAlloc/RBF-v0", entity_rows=tuple(range(n)))  # RBF-v0 with its first n entities
            model = TwoStageSAC("TAMPolicy", env, learning_starts=64, batch_size=64, seed=0, device=device)
            rows.append(measure(model, device, steps // 2, f"RBF-v0, first {n} entities"))
    return rows


def bench_learn(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Wall-clock to a trained policy: TwoStageSAC on RBF at the zoo config (``--algo-kwargs`` over it) trains until its
    deterministic mean return on seed k's held-out episodes (those of ``experiments learn``) reaches
    :data:`LEARN_TARGET` × the same policy untrained on them, or ``--learn-steps`` env steps. It is evaluated every
    ``--eval-every`` env steps; the evaluations are not counted in the time. One row per training seed and device."""
    import envs  # noqa: F401
    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.experiments.budgets import over_zoo, training_env
    from sb3_taskalloc.experiments.evaluation import Curve, episode_returns, eval_seeds

    env_id = "TaskAlloc/RBF-v0"
    budget, every, episodes = (200, 100, 2) if args.quick else (args.learn_steps, args.eval_every, 10)
    if budget < 1 or every < 1:
        raise SystemExit(f"--learn-steps and --eval-every must be >= 1, got {budget} and {every}")

    class ToTarget(Curve):
        """The learning experiment's curve, timed: each evaluation (on passing a multiple of ``every`` env steps) runs
        with the training clock stopped (after the device's queued work), and training stops at the target. No
        evaluation at step 0: the untrained return is measured before."""

        def __init__(self, seeds: list[int], target: float) -> None:
            super().__init__(env_id, seeds, every)
            self.target, self.seconds, self.clock = target, 0.0, 0.0
            self.timed: list[tuple[int, float, float]] = []  # (env steps, training seconds, return), rounded

        @property
        def last(self) -> float:
            return self.points[-1][1]

        @property
        def reached(self) -> bool:
            return bool(self.points) and self.last >= self.target

        def _on_training_start(self) -> None:
            self.clock = time.perf_counter()

        def _evaluate(self) -> None:
            _sync(self.model.device.type)
            self.seconds += time.perf_counter() - self.clock
            super()._evaluate()
            self.timed.append((self.num_timesteps, round(self.seconds, 2), round(self.last, 2)))
            self.clock = time.perf_counter()

        def _on_step(self) -> bool:
            super()._on_step()
            return not self.reached

        def _on_training_end(self) -> None:  # the budget ran out between two evaluations: evaluate where it stopped
            if not self.points or self.points[-1][0] < self.num_timesteps:
                self._evaluate()

    hyperparameters = over_zoo(env_id, args.algo_kwargs)
    rows = []
    for device in _devices(args):
        for seed in range(args.seeds):
            env, kwargs = training_env(env_id, hyperparameters, seed)
            model = TwoStageSAC("TAMPolicy", env, seed=seed, device=device, **kwargs)
            seeds = eval_seeds(seed, episodes)
            untrained = float(np.mean(episode_returns(model, env_id, seeds)))
            callback = ToTarget(seeds, LEARN_TARGET * untrained)
            model.learn(budget, callback=callback)
            steps, seconds, _ = callback.timed[-1]
            reached, value = callback.reached, callback.last
            rows.append(
                {
                    "device": device,
                    "seed": seed,
                    "n_envs": model.n_envs,
                    "untrained": untrained,
                    "target_return": callback.target,
                    "reached": reached,
                    "seconds_to_target": seconds if reached else None,
                    "env_steps_to_target": steps if reached else None,
                    "last_return": value,
                    "last_ratio": value / untrained if untrained > 0 else None,
                    "training_s": seconds,  # rounded like the curve
                    "env_steps": steps,
                    "curve": callback.timed,
                }
            )
    return rows


def _amix_ms(model: TwoStageSAC, device: str, reps: int) -> float:
    """Median time of the AMIX work that every stage-1 gradient step must do (implementation details 1–3): the twin
    target mixers' self-attention hypernetworks on the next states (no gradient) and the twin online mixers' forward
    and backward passes, on a batch of the size of the training step. The rest of the step (encoders, actor, select
    stage) is left out, so this is a lower bound on the gradient step and ``1000 / (decision + this)`` an upper bound
    on the env steps/s that this architecture reaches on the device."""
    import torch as th

    online, target = model.critic, model.critic_target
    assert online is not None and target is not None, "the train benchmark times TwoStageSAC with pre-assignment"
    data = model.replay_buffer.sample(model.batch_size)
    view, next_view = model.policy.parse(data.observations), model.policy.parse(data.next_observations)
    q_i = th.ones(view.entity.shape[:2], device=view.entity.device)  # per-entity values: the mixers' work ignores them

    def amix() -> None:
        with th.no_grad():
            for critic in target.q_networks:
                critic.mixer(q_i, next_view)  # type: ignore[operator]
        th.stack([critic.mixer(q_i, view) for critic in online.q_networks]).sum().backward()  # type: ignore[operator]
        _sync(device)

    ms = _median_ms(amix, reps, warmup=1)
    online.optimizer.zero_grad()  # the timed backward passes leave no gradient behind
    return ms


def bench_baselines(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Seconds per decision of every baseline and of TwoStageSAC on RBF (planners at the budget the experiments use
    and at the paper's settings), and MILP solve time against the instance size."""
    import gymnasium as gym
    import torch as th

    import envs  # noqa: F401
    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.baselines import (
        GeneticAlgorithm,
        GreedyAllocator,
        MILPAllocator,
        ParticleSwarm,
        RecedingHorizonPlanner,
        SymbioticOrganismsSearch,
    )
    from sb3_taskalloc.experiments.budgets import PLANNER_BUDGET

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
    rows.append({"method": "MILP", "setting": "time_limit 10 s", "s_per_decision": per_decision(lambda env: MILPAllocator())})
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
        env = _scaled_rbf(n, m)
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


BENCHES: dict[str, BenchFn] = {
    "envs": bench_envs,
    "policy": bench_policy,
    "train": bench_train,
    "baselines": bench_baselines,
    "learn": bench_learn,
    "labels": bench_labels,
}


def _print_table(name: str, rows: list[dict[str, Any]]) -> None:
    if not rows:
        return
    keys = list(dict.fromkeys(key for row in rows for key in row))  # every column, in order of first appearance
    print(f"\n## {name}")
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for row in rows:
        cells = [_cell(row.get(key)) for key in keys]
        print("| " + " | ".join(cells) + " |")


def _cell(v: Any) -> str:
    """A table cell: 3 significant digits below 100, whole numbers above, blank for a missing value."""
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:,.3g}" if abs(v) < 100 else f"{v:,.0f}"
    if isinstance(v, list) and len(v) > 4:  # a curve: in the JSON
        return f"{len(v)} points"
    return str(v)


def main(argv: list[str] | None = None) -> None:
    from sb3_taskalloc.experiments.budgets import yaml_mapping

    parser = argparse.ArgumentParser(prog="python -m sb3_taskalloc.bench", description=__doc__)
    parser.add_argument("which", choices=[*BENCHES, "all"], help="benchmark to run")
    parser.add_argument("--out", default="bench_out", help="folder for the JSON results")
    parser.add_argument("--quick", action="store_true", help="shorter timings (smoke runs)")
    parser.add_argument(
        "--model", default=None, help="policy and labels benchmarks: a trained TwoStageSAC for the episode states"
    )
    parser.add_argument(
        "--train-steps",
        type=int,
        default=None,
        help="policy and labels benchmarks without --model: steps to train one first (default 3,000; 100 with --quick)",
    )
    parser.add_argument("--seeds", type=int, default=1, help="learn benchmark: training seeds 0 .. seeds - 1")
    parser.add_argument("--learn-steps", type=int, default=48_000, help="learn benchmark: env steps at most per seed")
    parser.add_argument("--eval-every", type=int, default=4_000, help="learn benchmark: env steps between evaluations")
    parser.add_argument(
        "--algo-kwargs", type=yaml_mapping, default={}, help="learn benchmark: TwoStageSAC keywords over the zoo config"
    )
    parser.add_argument(
        "--device",
        default="auto",
        choices=["auto", "cpu", "cuda"],
        help="devices for the policy and train benchmarks: auto = the CPU, plus CUDA when a GPU is available",
    )
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    names = list(BENCHES) if args.which == "all" else [args.which]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name in names:
        rows = BENCHES[name](args)
        _print_table(name, rows)
        record = {
            "benchmark": name,
            "command": "python -m sb3_taskalloc.bench " + shlex.join(sys.argv[1:] if argv is None else argv),
            "machine": _machine(),
            "torch_threads": torch.get_num_threads(),
            "results": rows,
        }
        (out / f"bench_{name}.json").write_text(json.dumps(record, indent=2))
        print(f"wrote {out / f'bench_{name}.json'}")


if __name__ == "__main__":
    main()
