"""Decisions recorded as CUDA graphs (``cuda_graph=True``, :mod:`sb3_taskalloc.two_stage_sac.graph_decide`): the
fixed-step decision they record is the eager one wherever its flag is clear and traces whole (on the CPU); on CUDA the
replayed argmax is the eager one, a team longer than the steps falls back to it, ``cuda_graph=True`` records samples
only, and training collects with them."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import torch._dynamo

import envs  # noqa: F401  (registers the TaskAlloc ids)
from sb3_taskalloc import TwoStageSAC
from sb3_taskalloc.common.torch_layers import ObsView
from sb3_taskalloc.experiments.bench.common import episode_states
from sb3_taskalloc.two_stage_sac.graph_decide import DecisionGraph, decide_fixed
from sb3_taskalloc.two_stage_sac.select_stage import Decision, decode_round

needs_cuda = pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA device")


def episode_views(model: TwoStageSAC, env_id: str, n: int, seed: int = 5) -> list[ObsView]:
    """The first ``n`` states of an episode the model's argmax plays (:func:`.episode_states`), parsed on the model's
    device."""
    with th.no_grad():
        return [model.policy.parse(model.policy.obs_to_tensor(obs)[0]) for obs in episode_states(model, env_id, [seed], n)]


def same(a: Decision, b: Decision) -> bool:
    return all(th.equal(x, y) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize("env_id", ["TaskAlloc/RBF-v0", "TaskAlloc/MT-v0"])
def test_a_fixed_step_decision_is_the_eager_one_where_its_flag_is_clear(env_id):
    """Over 12 states of an episode of the zoo's policy (4 rounds): 32 steps per round decide as the eager argmax with
    the flag clear; 2 steps leave a team unfinished in some state (the flag set), and decide alike wherever it is
    clear. A sample's first round is the eager sample's from the same seed (later rounds draw after a different number
    of picks). The whole fixed-step decision traces as one graph with no break (what a CUDA graph records)."""
    model = TwoStageSAC.from_zoo(env_id, seed=0, n_envs=1, device="cpu")
    policy, flags, views = model.policy, [], episode_views(model, env_id, 12)
    assert len(views) == 12  # the episode's first 12 states: it stops there
    for view in views:
        with th.inference_mode():
            eager = policy.decide(view, deterministic=True)
            fixed, unfinished = decide_fixed(policy, view, True, 32)
            assert not bool(unfinished) and same(eager, fixed)
            short, unfinished = decide_fixed(policy, view, True, 2)
            flags.append(bool(unfinished))
            assert unfinished or same(eager, short)
            th.manual_seed(1)
            sampled = policy.decide(view, deterministic=False)
            th.manual_seed(1)
            fixed, unfinished = decide_fixed(policy, view, False, 32)
            assert not bool(unfinished)
            assert th.equal(sampled.candidates, fixed.candidates) and th.equal(sampled.pick_rank, fixed.pick_rank)
    assert any(flags)
    with th.no_grad():
        explained = torch._dynamo.explain(lambda v: decide_fixed(policy, v, True, 3))(view)
    assert explained.graph_count == 1 and explained.graph_break_count == 0, explained.break_reasons


def test_steps_bound_the_fixed_loop_only():
    """``decode_round(steps=...)`` without ``fixed_picks`` is refused with a clear error."""
    model = TwoStageSAC.from_zoo("TaskAlloc/MT-v0", seed=0, n_envs=1, device="cpu")
    view = episode_views(model, "TaskAlloc/MT-v0", 1)[0]
    task_of = th.zeros(view.entity_mask.shape, dtype=th.long)
    with pytest.raises(ValueError, match="fixed_picks=True"), th.no_grad():
        decode_round(model.policy.selector.head, view, task_of, True, steps=4)


def test_a_decision_graph_needs_steps():
    """A budget of no pick steps is refused with a clear error."""
    with pytest.raises(ValueError, match="steps"):
        DecisionGraph(0)


def test_cuda_graph_decides_eagerly_off_cuda():
    """``cuda_graph=True`` gives the policy a :class:`DecisionGraph`, which declines on the CPU: the same decisions as a
    model without it, none recorded."""
    plain = TwoStageSAC.from_zoo("TaskAlloc/MT-v0", seed=0, n_envs=1, device="cpu")
    graphed = TwoStageSAC.from_zoo("TaskAlloc/MT-v0", seed=0, n_envs=1, device="cpu", cuda_graph=True)
    assert plain.policy.decision_graph is None and isinstance(graphed.policy.decision_graph, DecisionGraph)
    obs, _ = gym.make("TaskAlloc/MT-v0").reset(seed=2)
    assert np.array_equal(plain.predict(obs, deterministic=True)[0], graphed.predict(obs, deterministic=True)[0])
    assert not graphed.policy.decision_graph.recorded and graphed.policy.decision_graph.replays == 0


@needs_cuda
@pytest.mark.parametrize("env_id", ["TaskAlloc/RBF-v0", "TaskAlloc/MT-v0"])
def test_cuda_recorded_decisions_are_the_eager_ones(env_id):
    """On CUDA the replayed argmax is the eager argmax over an episode's states (one recording for the shape); with 2
    steps per round the long teams fall back to the eager decision, still the same; samples are valid decisions."""
    model = TwoStageSAC.from_zoo(env_id, seed=0, n_envs=1, device="cuda")
    policy = model.policy
    views = episode_views(model, env_id, 12)
    for steps in (32, 2):
        graph = DecisionGraph(steps, argmax=True)
        for view in views:
            with th.inference_mode():
                eager = policy.decide(view, deterministic=True)
                policy.decision_graph = graph
                recorded = policy.decide(view, deterministic=True)
                sampled = policy.decide(view, deterministic=False)
                policy.decision_graph = None
            assert same(eager, recorded)
            free, M = view.entity_mask, view.task_mask.shape[1]
            assert bool(((sampled.env_action == M) | free).all())  # only free entities are sent
        assert len(graph.recorded) == 2  # one shape, argmax and samples
        assert graph.fallbacks > 0 if steps == 2 else graph.replays > 0 and graph.fallbacks == 0
    with th.inference_mode():
        first = policy.decide(views[0], deterministic=True)
    policy.decision_graph = samples_only = DecisionGraph()  # as cuda_graph=True sets it: the argmax stays eager
    with th.inference_mode():
        assert same(policy.decide(views[0], deterministic=True), first)
        assert not samples_only.recorded
        policy.decide(views[0], deterministic=False)
    assert len(samples_only.recorded) == 1 and samples_only.replays == 1


@needs_cuda
def test_cuda_graph_training_collects_by_replays():
    """The zoo's MT block with ``cuda_graph=True`` on CUDA trains and collects its samples by replayed decisions."""
    model = TwoStageSAC.from_zoo("TaskAlloc/MT-v0", seed=0, device="cuda", cuda_graph=True, learning_starts=16)
    model.zoo_callbacks = ()  # no DAgger phase
    model.learn(64)
    graph = model.policy.decision_graph
    assert graph is not None and graph.replays > 0
