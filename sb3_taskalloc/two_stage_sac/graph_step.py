"""TwoStageSAC's gradient step: eager (the reference), or recorded once as a CUDA graph and replayed (``cuda_graph=True``,
implementation detail 26).

On CUDA an eager step is bound by the host: Python launches each of its thousands of small kernels (7,874 at RBF's zoo
block on an H200, for 16 ms of GPU work in 177 ms of wall time). A CUDA graph records the kernels of one step once, both
stages' losses laid out with fixed shapes (the ``padded`` updates of :mod:`.updates`), their backward passes and the
optimizers' steps (Adam with ``capturable=True``, its step count on the device), and replays them with one launch on
each new minibatch, copied into the recorded input tensors. The target networks' Polyak averaging stays outside it:
``target_update_interval`` may skip it. There the block's step takes 73 ms, 60 of them on the GPU, and training runs at
62.7 env steps/s against 31.3 eager (docs/benchmarks.md, "The gradient step as a CUDA graph").
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import torch as th

from sb3_taskalloc.common.buffers import TwoStageReplayBufferSamples
from sb3_taskalloc.two_stage_sac.updates import Logs, PreAssignUpdate, SelectUpdate, optimizers

if TYPE_CHECKING:
    from sb3_taskalloc.two_stage_sac.two_stage_sac import TwoStageSAC

#: Eager steps before the recording: they build the optimizers' state and the CUDA libraries' workspaces, which must
#: exist before a graph records (PyTorch's "whole-network capture" recipe warms up with three).
GRAPH_WARMUP = 3


class GradientStep:
    """One gradient step of each update on a sampled minibatch, run eagerly: the reference.

    :param model: the algorithm, whose policy parses the observations
    :param updates: the stages' updates, in order
    """

    def __init__(self, model: TwoStageSAC, updates: list[PreAssignUpdate | SelectUpdate]) -> None:
        self.model, self.updates = model, updates

    def __call__(self, data: TwoStageReplayBufferSamples, logs: Logs) -> None:
        obs = self.model.policy.parse(data.observations)  # type: ignore[arg-type]
        for update in self.updates:
            update(obs, data, logs)  # type: ignore[arg-type]


class CUDAGraphStep(GradientStep):
    """The gradient step recorded as a CUDA graph on the first step after :data:`GRAPH_WARMUP` eager ones (run on a
    side stream, as the recording will be), then replayed on each minibatch. The padded losses are the eager ones up
    to rounding (``tests/test_traced.py``); the team search draws its samples from the graph's own offsets of the CUDA
    random stream, so its teams are not the eager step's.

    :param model: the algorithm
    """

    def __init__(self, model: TwoStageSAC) -> None:
        super().__init__(model, padded_updates(model))
        self.calls = 0
        self.graph: th.cuda.CUDAGraph | None = None
        self.inputs: TwoStageReplayBufferSamples | None = None
        self.outputs: Logs = {}

    def make_capturable(self) -> None:
        """Adam with its step count on the device (``capturable``), which the graph increments: set here rather than
        at construction, since ``load`` restores the saved (eager) optimizer settings after it. Idempotent."""
        for optimizer in optimizers(self.model):
            for group in optimizer.param_groups:
                group["capturable"] = True
                for param in group["params"]:
                    state = optimizer.state.get(param, {})
                    if "step" in state:
                        state["step"] = state["step"].to(param.device, th.float32)

    def __call__(self, data: TwoStageReplayBufferSamples, logs: Logs) -> None:
        if self.inputs is not None and shapes(self.inputs) != shapes(data):
            self.graph, self.inputs, self.calls = None, None, 0  # another batch size or env size: warm up, record anew
        if self.graph is None and self.calls < GRAPH_WARMUP:
            if self.calls == 0:
                self.make_capturable()
            self.calls += 1
            on_side_stream(lambda: super(CUDAGraphStep, self).__call__(data, logs))
            return
        if self.graph is None:
            self.record(data)
        else:
            copy_into(self.inputs, data)  # type: ignore[arg-type]
        assert self.graph is not None
        self.graph.replay()
        for key, values in self.outputs.items():
            logs[key].extend(value.clone() for value in values)  # the graph overwrites its outputs at the next replay

    def record(self, data: TwoStageReplayBufferSamples) -> None:
        """Record one step on ``data``, whose tensors become the graph's inputs (recording runs nothing)."""
        for optimizer in optimizers(self.model):
            optimizer.zero_grad(set_to_none=True)  # the graph's backward passes allocate the gradients in its pool
        outputs: Logs = defaultdict(list)
        self.inputs, self.graph = data, th.cuda.CUDAGraph()
        with th.cuda.graph(self.graph):
            super().__call__(data, outputs)
        self.outputs = dict(outputs)


def padded_updates(model: TwoStageSAC) -> list[PreAssignUpdate | SelectUpdate]:
    """The model's updates laid out with fixed shapes and no host read (``padded=True``): what a CUDA graph records."""
    return [type(update)(model, padded=True) for update in model.updates]


def _tensors(data: tuple[Any, ...]) -> Iterator[th.Tensor]:
    for field in data:
        if isinstance(field, dict):
            yield from field.values()
        elif field is not None:
            yield field


def shapes(data: tuple[Any, ...]) -> list[tuple[int, ...]]:
    """The shapes of a recorded graph's inputs (a minibatch, an :class:`~.ObsView`: a tuple of tensors, dicts of
    tensors or None), which the graph is bound to."""
    return [tuple(x.shape) for x in _tensors(data)]


def copy_into(inputs: tuple[Any, ...], data: tuple[Any, ...]) -> None:
    """Copy new inputs into a recorded graph's input tensors (of the same shapes, :func:`shapes`)."""
    for old, new in zip(_tensors(inputs), _tensors(data), strict=True):
        old.copy_(new, non_blocking=True)


def on_side_stream(run: Callable[[], object]) -> None:
    """``run()`` on a new CUDA stream after the current stream's work, which then waits for it: how the eager runs
    before a recording go (PyTorch's whole-network capture recipe)."""
    side = th.cuda.Stream()
    side.wait_stream(th.cuda.current_stream())
    with th.cuda.stream(side):
        run()
    th.cuda.current_stream().wait_stream(side)


def gradient_step(model: TwoStageSAC) -> GradientStep:
    """The model's gradient step: recorded as a CUDA graph where ``cuda_graph`` is set and the model trains on CUDA,
    eager elsewhere (a CUDA graph runs on CUDA alone)."""
    if model.cuda_graph and model.device.type == "cuda":
        return CUDAGraphStep(model)
    return GradientStep(model, model.updates)


def check_cuda_graph(model: TwoStageSAC) -> None:
    """A clear error where ``cuda_graph=True`` cannot record the step, on any device: a learning-rate schedule (the
    graph records the optimizers' steps with one rate)."""
    if not model.cuda_graph:
        return
    if callable(model.learning_rate):
        raise ValueError(
            "cuda_graph=True records the optimizers' steps with one learning rate: use a constant learning_rate, not "
            f"a schedule ({model.learning_rate!r}), or cuda_graph=False"
        )


class GraphStepMixin:
    """For :class:`~sb3_taskalloc.TwoStageSAC`: its parameters saved and loaded around a CUDA graph step."""

    gradient_step: GradientStep

    def get_parameters(self) -> dict[str, dict]:
        """SB3's, with the optimizers saved as eager ones (``capturable`` off, which a CUDA graph step sets): Adam
        refuses it on the CPU, and the saved model loads and trains on any device."""
        parameters: dict[str, dict] = super().get_parameters()  # type: ignore[misc]
        for state in parameters.values():
            for group in state.get("param_groups", ()):
                if group.get("capturable"):
                    group["capturable"] = False  # a copy: ``state_dict`` copies each group's settings
        return parameters

    def set_parameters(self, load_path_or_dict: Any, exact_match: bool = True, device: th.device | str = "auto") -> None:
        """SB3's, then a new gradient step where a CUDA graph was recorded: loading replaces the optimizers' state
        tensors, which the recorded graph would go on reading and writing."""
        super().set_parameters(load_path_or_dict, exact_match, device)  # type: ignore[misc]
        if isinstance(getattr(self, "gradient_step", None), CUDAGraphStep):
            self.gradient_step = gradient_step(self)  # type: ignore[arg-type]
