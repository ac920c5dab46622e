"""The gradient step recorded as a CUDA graph (``cuda_graph=True``, :mod:`sb3_taskalloc.two_stage_sac.graph_step`): the
padded step it records is the eager step up to rounding (on the CPU), its settings are checked on any device, a model
trained with it saves eager optimizers, and on CUDA the replayed graph is the padded step run eagerly."""

from __future__ import annotations

import warnings
from collections import defaultdict
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th

import envs  # noqa: F401  (registers the TaskAlloc ids)
from sb3_taskalloc import TwoStageSAC
from sb3_taskalloc.two_stage_sac import graph_step

needs_cuda = pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA device")


def filled(device: str = "cpu", search: bool = True, **policy_kwargs: Any) -> TwoStageSAC:
    """RBF with its first 12 robots, both stages trained, the team search on (or off); 48 warm-up steps stored."""
    env = gym.make("TaskAlloc/RBF-v0", entity_rows=tuple(range(12)))
    select = {"search_coef": 30.0 if search else 0.0, "search_samples": 8}
    model = TwoStageSAC(
        "TAMPolicy", env, learning_starts=48, seed=0, device=device, select_kwargs=select, policy_kwargs=policy_kwargs
    )
    with warnings.catch_warnings():  # the warm-up alone: decisions stored, nothing trained
        warnings.simplefilter("ignore", UserWarning)
        model.learn(48)
    return model


def run_steps(
    model: TwoStageSAC, step: graph_step.GradientStep, n: int, rows: int = 16, first: int = 0
) -> dict[str, list[float]]:
    """``n`` gradient steps of ``step`` on the minibatches and random streams of seeds first..first+n−1; the logged
    values."""
    logs: dict[str, list[th.Tensor]] = defaultdict(list)
    for k in range(first, first + n):
        np.random.seed(k)  # the replay buffer samples with numpy's global stream
        th.manual_seed(k)
        step(model.replay_buffer.sample(rows), logs)
    return {key: [float(v) for v in values] for key, values in logs.items()}


def assert_same_logs(a: dict[str, list[float]], b: dict[str, list[float]], rtol: float, atol: float) -> None:
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_allclose(a[key], b[key], rtol=rtol, atol=atol, err_msg=key)


def padded(model: TwoStageSAC) -> graph_step.GradientStep:
    return graph_step.GradientStep(model, graph_step.padded_updates(model))


def assert_same_models(a: TwoStageSAC, b: TwoStageSAC, tol: float) -> None:
    for (name, p), q in zip(a.policy.named_parameters(), b.policy.parameters(), strict=True):
        th.testing.assert_close(p, q, atol=tol, rtol=0, msg=name)


def assert_same_gradients(a: TwoStageSAC, b: TwoStageSAC, rtol: float) -> None:
    """Each parameter's gradient of the last step, up to ``rtol`` of the tensor's largest entry."""
    for (name, p), q in zip(a.policy.named_parameters(), b.policy.parameters(), strict=True):
        if p.grad is None or q.grad is None:
            assert p.grad is None and (q.grad is None or not q.grad.any()), name
            continue
        th.testing.assert_close(p.grad, q.grad, atol=rtol * float(p.grad.abs().max()) + 1e-12, rtol=0, msg=name)


def assert_padded_is_eager(eager: TwoStageSAC, pad: TwoStageSAC, n: int = 3) -> dict[str, list[float]]:
    """The padded step against the eager one from the same weights: the first step's gradients, then the logs of ``n``
    steps. Weights are not compared: Adam's normalised step turns a rounding-level difference in a gradient near 0
    into a difference of the learning rate's size, in either direction, on some CPUs."""
    logs = run_steps(eager, graph_step.GradientStep(eager, eager.updates), 1)
    padded_logs = run_steps(pad, padded(pad), 1)
    assert_same_gradients(eager, pad, 1e-4)
    for key, values in run_steps(eager, graph_step.GradientStep(eager, eager.updates), n - 1, first=1).items():
        logs[key] += values
    for key, values in run_steps(pad, padded(pad), n - 1, first=1).items():
        padded_logs[key] += values
    assert_same_logs(logs, padded_logs, 1e-5, 1e-6)
    return logs


def test_padded_gradient_step_is_the_eager_one():
    """What the graph records, the padded updates of both stages with the team search, run eagerly: the same losses,
    temperatures and search statistics as the eager step over three steps, and the same gradients, up to rounding."""
    eager, pad = filled(), filled()
    assert [type(u).__name__ for u in eager.updates] == ["PreAssignUpdate", "SelectUpdate"]
    logs = assert_padded_is_eager(eager, pad)
    assert logs["select_search_loss"][0] != 0  # the search found better teams: its term is in the step


def test_padded_gradient_step_is_the_eager_one_on_the_pointers_own_costs():
    """The zoo blocks' pointer decodes and trains on costed pairs (``select_values``, RBF's θ and MT's σ at once): the
    padded step reads the same costs as the eager one, so the graph records what the eager step trains."""
    values = {"theta": [-0.114, -0.041, 0.010], "surcharge": 0.64}
    eager, pad = filled(select_values=values), filled(select_values=values)
    logs = assert_padded_is_eager(eager, pad)
    plain = filled()
    assert logs["select_actor_loss"] != run_steps(plain, graph_step.GradientStep(plain, plain.updates), 3)["select_actor_loss"]


def test_cuda_graph_settings_are_checked_on_every_device():
    """``cuda_graph`` is a bool; it needs a constant learning rate, and says so on any device. On the CPU the model
    trains with the eager step."""
    env = gym.make("TaskAlloc/Almighty-v0")
    with pytest.raises(ValueError, match="cuda_graph must be True or False"):
        TwoStageSAC("TAMPolicy", env, cuda_graph="yes", device="cpu")
    with pytest.raises(ValueError, match="constant learning_rate, not a schedule"):
        TwoStageSAC("TAMPolicy", env, cuda_graph=True, learning_rate=lambda progress: 1e-3 * progress, device="cpu")
    model = TwoStageSAC("TAMPolicy", env, cuda_graph=True, learning_starts=10, device="cpu", seed=0)
    assert type(model.gradient_step) is graph_step.GradientStep
    model.learn(30)
    assert model._n_updates == 20


def test_a_model_saves_eager_optimizers(tmp_path):
    """A graph step's optimizers are ``capturable`` (their step counts on the device), which Adam refuses on the CPU:
    the saved model keeps the live one's state but not that flag, and loads and trains on the CPU. Loading parameters
    into a model rebuilds its graph step."""
    model = filled()
    model.learn(8, reset_num_timesteps=False)
    graph_step.CUDAGraphStep(model).make_capturable()  # what the first graph step does (on CUDA)
    assert all(group["capturable"] for group in model.selector.optimizer.param_groups)
    model.save(tmp_path / "m")
    assert model.selector.optimizer.param_groups[0]["capturable"]  # the live model is left as it was
    loaded = TwoStageSAC.load(tmp_path / "m", env=model.get_env(), device="cpu")
    groups = [g for opt in (loaded.selector.optimizer, loaded.critic.optimizer) for g in opt.param_groups]
    assert groups and not any(group["capturable"] for group in groups)
    saved, live = (m.selector.optimizer.state_dict()["state"][0]["exp_avg"] for m in (loaded, model))
    th.testing.assert_close(saved, live)
    loaded.learn(8, reset_num_timesteps=False)
    assert loaded._n_updates == model._n_updates + 8
    # Loading parameters into a model replaces its optimizers' state tensors: a recorded graph step is rebuilt.
    recorded = model.gradient_step = graph_step.CUDAGraphStep(model)
    model.set_parameters(str(tmp_path / "m"))
    assert model.gradient_step is not recorded


@needs_cuda
def test_cuda_graph_replays_the_padded_step():
    """On CUDA, the warm-up steps, the recording and its replays on new minibatches give the losses and weights of the
    padded step run eagerly, up to rounding (no team search: its samples come from other offsets of the random stream)."""
    eager, graphed = (filled("cuda", search=False) for _ in range(2))
    step = graph_step.CUDAGraphStep(graphed)
    assert step.graph is None
    logs = run_steps(graphed, step, graph_step.GRAPH_WARMUP + 3)
    assert step.graph is not None and step.calls == graph_step.GRAPH_WARMUP
    assert_same_logs(run_steps(eager, padded(eager), graph_step.GRAPH_WARMUP + 3), logs, 1e-4, 1e-5)
    assert_same_models(eager, graphed, 1e-4)
    # Minibatches of another size: warmed up and recorded anew.
    first = step.graph
    more = run_steps(graphed, step, graph_step.GRAPH_WARMUP + 2, rows=8)
    assert step.graph is not None and step.graph is not first
    assert all(np.isfinite(values).all() for values in more.values())


@needs_cuda
def test_cuda_graph_trains_the_zoo_block_and_loads_on_the_cpu(tmp_path):
    """RBF's zoo block with ``cuda_graph=True`` on CUDA: the step is recorded, training runs with finite losses and
    changes the pointer, and the model loads and acts on the CPU."""
    model = TwoStageSAC.from_zoo("TaskAlloc/RBF-v0", seed=0, learning_starts=64, cuda_graph=True, device="cuda")
    model.zoo_callbacks = ()  # no DAgger phase
    before = [p.detach().clone() for p in model.selector.parameters()]
    model.learn(8 * 20)  # 12 gradient steps: the warm-up, the recording, 8 replays
    assert isinstance(model.gradient_step, graph_step.CUDAGraphStep) and model.gradient_step.graph is not None
    assert any(not th.equal(p, q) for p, q in zip(before, model.selector.parameters(), strict=True))
    model.save(tmp_path / "m")
    loaded = TwoStageSAC.load(tmp_path / "m", device="cpu")
    obs = gym.make("TaskAlloc/RBF-v0").reset(seed=0)[0]
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])


def test_cuda_graph_keeps_the_digests_of_results():
    """``cuda_graph`` changes no CPU result, so its default is not part of a result's digest (earlier results stay
    valid); set in a run's keywords, it files that run apart."""
    from sb3_taskalloc.experiments.budgets import code_defaults
    from sb3_taskalloc.experiments.learn import LearnRun

    assert "cuda_graph" not in code_defaults()["TwoStageSAC"] and "tau" in code_defaults()["TwoStageSAC"]
    run = LearnRun(env="Almighty", steps=600, eval_episodes=2, eval_every=600, planners=())
    assert (
        run.key
        != LearnRun(
            env="Almighty", steps=600, eval_episodes=2, eval_every=600, planners=(), algo_kwargs={"cuda_graph": True}
        ).key
    )
