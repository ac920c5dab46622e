"""Decision latency: the policy over real RBF episode states and at scale, each decoding strategy, and the exact
covers that label DAgger."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np

from sb3_taskalloc.experiments.bench.common import (
    bench_devices,
    episode_states,
    median_ms,
    rbf_model,
    scaled_rbf,
    state_latencies_ms,
    sync,
)
from sb3_taskalloc.two_stage_sac.settings import RECOMMENDED_DECODERS

#: Pre-assignments of the decision-time search row (the ``preassign_search`` decoder; implementation detail 16).
SEARCH = 32


#: Teams per task of the decision-time team search row (the ``team_search`` decoder; implementation detail 20).
TEAM_SEARCH = 64


#: The trained policy's rows: its decoding strategies by name (:mod:`~sb3_taskalloc.two_stage_sac.decoding`) with
#: their settings; :func:`decoder_words` names each row from them.
DECODER_ROWS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("argmax", {}),
    ("preassign_search", {"samples": SEARCH}),
    ("team_search", {"samples": TEAM_SEARCH}),
    ("exact_covers", {}),
    ("exact_top", {"top": 1}),
    ("exact_top", {"top": 2}),
    RECOMMENDED_DECODERS["TaskAlloc/RBF-v0"],
)

#: MT's recommended decoder and its settings.
MT_DECODER: tuple[str, dict[str, Any]] = RECOMMENDED_DECODERS["TaskAlloc/MT-v0"]


def decoder_words(decoder: str, config: dict[str, Any], n_tasks: int) -> str:
    """The words a decoder's row adds to the policy's name, built from its settings, so that a row is renamed when a
    setting (a recommended decoder's, say) changes.

    :param decoder: the strategy's name
    :param config: its keyword arguments (the strategy's defaults fill the rest)
    :param n_tasks: the env's task slots M: ``exact_top`` with ``top`` ≥ M takes every pair
    """
    from sb3_taskalloc.two_stage_sac.decoding import get_decoding_strategy

    config = get_decoding_strategy(decoder, **config).config
    if decoder in ("exact_top", "entity_value"):
        top, surcharge = config["top"], config["surcharge"]
        among = "every pair" if top >= n_tasks else "each entity's top task" if top == 1 else f"each entity's top {top} tasks"
        words = f", exact pre-assignment among {among}" + (f", {100 * surcharge:g} % surcharge" if surcharge else "")
        return words + (", learned entity values" if decoder == "entity_value" else "")
    if decoder in ("preassign_search", "team_search"):
        return f", {'team search' if decoder == 'team_search' else 'search'} of {config['samples']}"
    return {"argmax": "", "exact_covers": ", exact covers"}[decoder]


def latency_fields(ms: np.ndarray) -> dict[str, Any]:
    """A latency row's figures: how many states were timed, and the median and p90 of their ms per decision."""
    return {"states": len(ms), "median_ms": float(np.median(ms)), "p90_ms": float(np.percentile(ms, 90))}


def recorded_fields(policy: Any, timed: Callable[[], np.ndarray]) -> dict[str, Any]:
    """``timed()``'s figures with ``policy``'s argmax decisions recorded as CUDA graphs
    (``DecisionGraph(argmax=True)``), and how many decisions replayed and fell back to the eager path."""
    from sb3_taskalloc.two_stage_sac.graph_decide import DecisionGraph

    graph = policy.decision_graph = DecisionGraph(argmax=True)
    try:
        ms = timed()
    finally:
        policy.decision_graph = None
    return {**latency_fields(ms), "replays": graph.replays, "fallbacks": graph.fallbacks}


def smoke_states(states: list[Any]) -> list[Any]:
    """``--quick``'s states: every eighth state of an episode's second half (the exact decoders take up to seconds on
    its first states, where most entities are free)."""
    return states[len(states) // 2 :: 8]


def bench_policy_mt(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Decision latency of MT's recommended decoder over the states of seeded MT episodes it plays, on the CPU, beside
    the argmax over the same states. The policy is untrained: with the pre-assign actor held at its rule, as in MT's
    zoo block, ``exact_top`` decides alike with a trained and an untrained policy (docs/learning.md)."""
    import gymnasium as gym
    import torch as th

    from sb3_taskalloc import TwoStageSAC

    env_id = "TaskAlloc/MT-v0"
    th.manual_seed(0)
    model = TwoStageSAC("TAMPolicy", gym.make(env_id), seed=0, device="cpu")
    decoder, config = MT_DECODER
    words = decoder_words(decoder, config, model.observation_space["task_mask"].shape[0])  # type: ignore[index]
    if args.quick:  # a smoke run: an episode the argmax plays, subsampled as on RBF
        states = smoke_states(episode_states(model, env_id, [30_000]))
    else:
        with model.decoding(decoder, **config):
            states = episode_states(model, env_id, [30_000, 30_001, 30_002])
    rows = []
    for name, kwargs, label in (("argmax", {}, ""), (decoder, config, words)):
        with model.decoding(name, **kwargs):
            ms = state_latencies_ms(model, states)
        rows.append({"device": "cpu", "env": env_id, "policy": f"TAMPolicy untrained{label}", "decoder": name,
                     **latency_fields(ms), "mean_ms": float(np.mean(ms))})  # fmt: skip
    return rows


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
    trained, source = rbf_model(args)
    th.manual_seed(0)
    untrained = TwoStageSAC("TAMPolicy", gym.make(env_id), seed=0, device="cpu")
    states = episode_states(trained, env_id, seeds)
    if args.quick:
        states = smoke_states(states)
    n_tasks = trained.observation_space["task_mask"].shape[0]
    searched = [("trained", trained, name, config, decoder_words(name, config, n_tasks)) for name, config in DECODER_ROWS]
    rows = []
    for device in devices:
        for name, agent, decoder, config, words in [searched[0], ("untrained", untrained, "argmax", {}, ""), *searched[1:]]:
            agent.policy.to(device)
            agent.device = th.device(device)
            with agent.decoding(decoder, **config):
                ms = state_latencies_ms(agent, states, device)
            rows.append(
                {"device": device, "env": env_id, "policy": f"TAMPolicy {name}{words}", "decoder": decoder,
                 **latency_fields(ms), "model": source if name == "trained" else None,
                 "target": "median <= 5 ms, p90 <= 10 ms (CPU)" if decoder == "argmax" else None}
            )  # fmt: skip
            if device == "cuda" and decoder == "argmax":
                fields = recorded_fields(agent.policy, partial(state_latencies_ms, agent, states, "cuda"))
                rows.append({**rows[-1], "policy": f"TAMPolicy {name}, recorded (cuda_graph=True)", **fields,
                             "target": "median <= the CPU's argmax"})  # fmt: skip
    ms = state_latencies_ms(GreedyAllocator(), states)
    rows.append({"device": "cpu", "env": env_id, "policy": "Greedy", **latency_fields(ms)})
    return rows


def bench_labels(args: argparse.Namespace) -> list[dict[str, Any]]:
    """The exact covers that label the pointer's DAgger (:meth:`~sb3_taskalloc.TwoStageSAC.distill_select`): every
    pre-assign round of seeded RBF episodes of a trained model's deterministic policy (``--model``), covered task by
    task (branch and bound, :func:`~sb3_taskalloc.baselines.milp.max_profit_team`) and by one HiGHS solve per round
    (the per-step MILP's formulation on the candidate pairs): seconds per round of each, and the largest difference
    between the two covers' profits (both exact: 0 up to the solvers' tolerances)."""
    import torch as th

    from sb3_taskalloc.two_stage_sac.search import exact_covers

    model, source = rbf_model(args)
    policy = model.policy
    rounds: list[tuple[Any, th.Tensor]] = []
    for obs in episode_states(model, "TaskAlloc/RBF-v0", [30_000] if args.quick else [30_000, 30_001, 30_002]):
        with th.inference_mode():
            policy.decide(policy.parse(policy.obs_to_tensor(obs)[0]), deterministic=True, rounds_out=rounds)
    rounds = rounds[:5] if args.quick else rounds  # a smoke run: the HiGHS reference takes about a second per round
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
    """TAMPolicy decision latency: over the states of seeded RBF episodes (:func:`bench_policy_episodes`) and of MT
    episodes with MT's recommended decoder (:func:`bench_policy_mt`), then on one reset RBF observation, a batch of
    256, and the N × M scaling table of reset states (CPU; CUDA when available)."""
    import torch as th
    from stable_baselines3.common.utils import obs_as_tensor

    from sb3_taskalloc import TAMPolicy

    devices = bench_devices(args)
    rows: list[dict[str, Any]] = bench_policy_episodes(args, devices) + bench_policy_mt(args)
    sizes = [(100, 10)] + [(n, m) for n in (50, 100, 500, 1000) for m in (5, 10, 50)]
    if args.quick:
        sizes = [(100, 10), (50, 5)]
    for device in devices:
        for i, (n, m) in enumerate(sizes):
            env = scaled_rbf(n, m)
            obs, _ = env.reset(seed=0)
            th.manual_seed(0)
            policy = TAMPolicy(env.observation_space, env.action_space, lambda _: 3e-4).to(device)  # type: ignore[arg-type]
            policy.set_training_mode(False)
            reps = 5 if (args.quick or n * m >= 50_000) else 30
            row: dict[str, Any] = {"device": device, "entities": n, "tasks": m}
            row["predict_ms"] = median_ms(lambda: policy.predict(obs, deterministic=True), reps)  # noqa: B023
            if device == "cuda":  # the same decision recorded as a CUDA graph, its median over ``reps`` replays

                def replayed(policy: TAMPolicy = policy, obs: Any = obs, reps: int = reps) -> np.ndarray:
                    return np.array([median_ms(lambda: policy.predict(obs, deterministic=True), reps)])

                fields = recorded_fields(policy, replayed)
                row.update(recorded_predict_ms=fields["median_ms"], recorded_fallbacks=fields["fallbacks"])
            if i == 0:
                batch = obs_as_tensor({k: np.repeat(v[None], 256, 0) for k, v in obs.items()}, th.device(device))

                def decide_batch(policy: TAMPolicy = policy, batch: Any = batch, device: str = device) -> None:
                    with th.no_grad():
                        policy.decide(policy.parse(batch), deterministic=True)
                        sync(device)

                row["batch256_ms_per_obs"] = median_ms(decide_batch, 3 if args.quick else 10, warmup=1) / 256
                row["target"] = "predict <= 5 ms, batch 256 <= 0.5 ms/obs"
            rows.append(row)
    return rows
