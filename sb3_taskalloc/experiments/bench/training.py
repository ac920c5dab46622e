"""Training throughput (env steps per second, gradient step time, CUDA launches) and wall-clock to a learned policy."""

from __future__ import annotations

import argparse
import time
import warnings
from typing import TYPE_CHECKING, Any

import numpy as np

from sb3_taskalloc.experiments.evaluation import Curve

if TYPE_CHECKING:
    from sb3_taskalloc import TwoStageSAC

from sb3_taskalloc.experiments.bench.common import bench_devices, median_ms, sync

#: The profiler's names of the host calls that launch a CUDA kernel, or a CUDA graph of them (one launch per replay).
LAUNCH_EVENTS = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx", "cudaGraphLaunch")


#: ``bench learn`` trains until the policy returns this multiple of its untrained initialisation.
LEARN_TARGET = 1.05


def measure_training(
    model: TwoStageSAC, device: str, steps: int, blocks: int, env: str, target: int | None = None
) -> dict[str, Any]:
    """One row: env steps/s of ``learn`` (the median of ``blocks`` runs of ``steps`` steps), then the gradient step
    and the stochastic decision timed apart (medians over single steps)."""
    with warnings.catch_warnings():  # the warm-up: no gradient step yet, as the warning says
        warnings.simplefilter("ignore", UserWarning)
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
        sync(device)

    def decision() -> None:
        model._sample_action(learning_starts=0)
        sync(device)

    grad_ms = median_ms(gradient_step, reps, warmup=1)  # the warm-up step also waits for learn()'s queued work
    decision_ms = median_ms(decision, reps, warmup=1)
    # AMIX trains only where the pre-assign actor learns (a held actor's critics do not train: detail 23).
    amix_ms = _amix_ms(model, device, reps) if model.train_preassign_actor else None
    kernel_ms = launches = None
    if device == "cuda":  # how much of the gradient step the GPU computes, apart from the host's dispatch
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            model.train(gradient_steps=reps, batch_size=64)
            sync(device)
        events = prof.key_averages()
        kernel_ms = sum(e.self_device_time_total for e in events if e.device_type.name == "CUDA") / reps / 1e3
        launches = sum(e.count for e in events if e.key in LAUNCH_EVENTS) / reps
    return {
        "device": device,
        "env": env,
        "config": "constructor defaults",
        "env_steps_per_s": rate,
        "env_steps_per_s_blocks": [round(r, 2) for r in rates],
        "minutes_to_100k_steps": 1e5 / rate / 60,  # extrapolated from the rate, for RBF's paper budget
        "gradient_step_ms": grad_ms,
        "gpu_kernel_ms_per_gradient_step": kernel_ms,
        "kernel_launches_per_gradient_step": launches,
        "decision_ms": decision_ms,
        "amix_ms_per_gradient_step": amix_ms,
        # What the decision and AMIX's attention alone would allow, with everything else in a step free.
        "env_steps_per_s_bound": 1e3 / (decision_ms + amix_ms) if amix_ms is not None else None,
        "replay_GB_for_100k": model.replay_buffer.nbytes_per_transition() * 100_000 / 1e9,
        "target_steps_per_s": target,
    }


def bench_train(args: argparse.Namespace) -> list[dict[str, Any]]:
    """TwoStageSAC training throughput: env steps/s with one gradient step (batch 64) per collection step (the median of
    three blocks of ``learn``, each block recorded; one env, and on RBF also ``n_envs=8``, where one step collects 8
    transitions with one batched decision) and the minutes that rate needs for 100,000 env steps; the gradient step
    and the stochastic decision timed apart; replay memory; and the gradient step on RBF scaled to fewer entities (what
    a step costs apart from the entity count). On CUDA, also the GPU kernel time and the kernel launches per gradient
    step (``torch.profiler``; ``None`` on the CPU), and each zoo block again with ``cuda_graph=True``."""
    import gymnasium as gym
    from stable_baselines3.common.env_util import make_vec_env

    from sb3_taskalloc import TwoStageSAC

    devices = bench_devices(args)
    rows = []
    steps = 8 if args.quick else 100
    blocks = 1 if args.quick else 3  # the median of three blocks damps the run-to-run spread of one block
    for device in devices:
        for env_id in ("TaskAlloc/RBF-v0", "TaskAlloc/EPT-v0", "TaskAlloc/MT-v0", "TaskAlloc/Almighty-v0"):
            if args.quick and env_id != "TaskAlloc/RBF-v0":
                continue
            model = TwoStageSAC("TAMPolicy", gym.make(env_id), learning_starts=64, batch_size=64, seed=0, device=device)
            rows.append(measure_training(model, device, steps, blocks, env_id, 60 if env_id == "TaskAlloc/RBF-v0" else None))
            rows.append(zoo_block_row(env_id, device, steps, blocks, dagger=not args.quick))
            if device == "cuda":  # the block as it trains best on a GPU: its gradient step replayed from a CUDA graph
                rows.append(zoo_block_row(env_id, device, steps, blocks, dagger=False, overrides={"cuda_graph": True}))
            if env_id == "TaskAlloc/RBF-v0":  # vectorised collection: one batched decision for n_envs envs
                for n_envs in () if args.quick else (8,):
                    vec = make_vec_env(env_id, n_envs=n_envs, seed=0)
                    model = TwoStageSAC("TAMPolicy", vec, learning_starts=64, batch_size=64, seed=0, device=device)
                    rows.append(measure_training(model, device, steps * n_envs // 2, blocks, f"{env_id}, n_envs={n_envs}", 60))
        for n in () if args.quick else (10, 25, 50):
            env = gym.make("TaskAlloc/RBF-v0", entity_rows=tuple(range(n)))  # RBF-v0 with its first n entities
            model = TwoStageSAC("TAMPolicy", env, learning_starts=64, batch_size=64, seed=0, device=device)
            rows.append(measure_training(model, device, steps // 2, blocks, f"RBF-v0, first {n} entities"))
    return rows


def bench_zoo(args: argparse.Namespace) -> list[dict[str, Any]]:
    """What users train: each env's recommended configuration (:func:`zoo_block_row`, ``--algo-kwargs`` over the
    block) on RBF and MT, as the train benchmark's zoo-block row times it."""
    steps, blocks = (8, 1) if args.quick else (100, 3)
    env_ids = ("TaskAlloc/RBF-v0", "TaskAlloc/MT-v0")  # not `envs`: zoo_block_row imports the package of that name
    return [
        zoo_block_row(env_id, device, steps, blocks, dagger=not args.quick, overrides=args.algo_kwargs)
        for device in bench_devices(args)
        for env_id in env_ids
    ]


def zoo_block_row(
    env_id: str, device: str, steps: int, blocks: int, dagger: bool, overrides: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The env's recommended configuration as users train it (:meth:`TwoStageSAC.from_zoo`: its zoo block, ``n_envs``
    included, ``overrides`` over it) timed like the defaults, with a 64-step warm-up; with ``dagger``, one iteration of
    the block's DAgger phase timed apart and the block's whole schedule (its budget, then its DAgger iterations)
    extrapolated."""
    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.zoo_config import zoo_dagger

    model = TwoStageSAC.from_zoo(env_id, seed=0, **{"learning_starts": 64, **(overrides or {}), "device": device})
    model.zoo_callbacks = ()  # the DAgger phase is timed apart
    n_envs = model.n_envs
    row = measure_training(model, device, max(steps, 8 * n_envs), blocks, f"{env_id}, zoo block (n_envs={n_envs})", 60)
    schedule = zoo_dagger(env_id)
    row.update(config="zoo block", dagger_iterations=schedule.get("iterations", 0), dagger_s_per_iteration=None)
    row.update(overrides=overrides or {})
    if dagger and schedule:
        t0 = time.perf_counter()
        model.distill_select(env_id, **{**schedule, "iterations": 1}, seed=0)
        row["dagger_s_per_iteration"] = time.perf_counter() - t0
    budget = model.zoo_n_timesteps or 0
    dagger_s = (row["dagger_s_per_iteration"] or 0.0) * row["dagger_iterations"]
    row["minutes_for_the_block"] = (budget / row["env_steps_per_s"] + dagger_s) / 60 if budget else None
    return row


class ToTarget(Curve):
    """The learning experiment's curve, timed: each evaluation (on passing a multiple of ``every`` env steps) runs
    with the training clock stopped (after the device's queued work), and training stops at the target. No
    evaluation at step 0: the untrained return is measured before."""

    def __init__(self, env_id: str, seeds: list[int], every: int, target: float) -> None:
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
        sync(self.model.device.type)
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


def bench_learn(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Wall-clock to a trained policy: TwoStageSAC on RBF at the zoo config (``--algo-kwargs`` over it) trains until its
    deterministic mean return on seed k's held-out episodes (those of ``experiments learn``) reaches
    :data:`LEARN_TARGET` × the same policy untrained on them, or ``--learn-steps`` env steps. It is evaluated every
    ``--eval-every`` env steps; the evaluations are not counted in the time. Then the block's DAgger phase runs, timed
    and evaluated on the same episodes apart. One row per training seed and device."""
    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.experiments.budgets import DAGGER_BUDGET
    from sb3_taskalloc.experiments.evaluation import episode_returns, eval_seeds
    from sb3_taskalloc.zoo_config import over_zoo, training_env, zoo_dagger

    env_id = "TaskAlloc/RBF-v0"
    # The block's DAgger phase after the training steps, timed and evaluated apart (--quick: the smoke budget's).
    schedule = {**zoo_dagger(env_id), **(DAGGER_BUDGET["smoke"] if args.quick else {})}
    budget, every, episodes = (200, 100, 1) if args.quick else (args.learn_steps, args.eval_every, 10)
    if budget < 1 or every < 1:
        raise SystemExit(f"--learn-steps and --eval-every must be >= 1, got {budget} and {every}")

    hyperparameters = over_zoo(env_id, args.algo_kwargs)
    rows = []
    for device in bench_devices(args):
        for seed in range(args.seeds):
            env, kwargs = training_env(env_id, hyperparameters, seed)
            model = TwoStageSAC("TAMPolicy", env, seed=seed, device=device, **kwargs)
            seeds = eval_seeds(seed, episodes)
            untrained = float(np.mean(episode_returns(model, env_id, seeds)))
            callback = ToTarget(env_id, seeds, every, LEARN_TARGET * untrained)
            model.learn(budget, callback=callback)
            steps, seconds, _ = callback.timed[-1]
            reached, value = callback.reached, callback.last
            after: dict[str, Any] = {"dagger_iterations": schedule.get("iterations", 0)}
            if schedule:
                t0 = time.perf_counter()
                model.distill_select(env_id, **schedule, seed=50_000 + seed)
                after["dagger_s"] = time.perf_counter() - t0
                after["after_dagger_return"] = float(np.mean(episode_returns(model, env_id, seeds)))
                after["after_dagger_ratio"] = after["after_dagger_return"] / untrained if untrained > 0 else None
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
                    **after,
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
        sync(device)

    ms = median_ms(amix, reps, warmup=1)
    online.optimizer.zero_grad()  # the timed backward passes leave no gradient behind
    return ms
