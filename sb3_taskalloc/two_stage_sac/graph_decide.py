"""TAMPolicy's decisions recorded as CUDA graphs (``TwoStageSAC(cuda_graph=True)``, implementation detail 29).

On CUDA an eager decision is bound by the host: the pointer decodes pick by pick, each pick launches a few dozen small
kernels, and the loop asks the host after each pick whether a task is still decoding. A recorded decision runs every
pre-assign round with no host check whether an entity is left, and decodes each round's teams by a fixed number of
pick steps (:data:`DECISION_STEPS`, ``decode_round(fixed_picks=True, steps=...)``), so one observation shape records
once and each later decision of that shape is one replay and one host read: whether some task was still decoding
after its round's steps. If one was, the decision is decided again eagerly, so a recorded decision is always the
eager one; for the argmax it is the same bit for bit, samples draw from the graph's offsets of the CUDA random stream.

Only the decisions the policy makes by itself are recorded: training's samples, and with ``DecisionGraph(argmax=True)``
the argmax decoder's. A search or exact decoder, the uniform warm-up and ``rounds_out`` stay eager. The fixed steps
cost GPU time where a round needs few picks. On an H200, RBF's zoo block (n_envs 8) decides in 38 against 58 ms and
trains at 68.6 against 55.2 env steps/s (the gradient step recorded in both); one observation's four-round argmax is
slower replayed than eager, and at 1000 entities × 50 tasks 3.4 times as fast (docs/benchmarks.md).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch as th

from sb3_taskalloc.common.torch_layers import ObsView
from sb3_taskalloc.common.utils import check_counts
from sb3_taskalloc.two_stage_sac.decoding import SAMPLED, Decoder, decide_preassigned
from sb3_taskalloc.two_stage_sac.graph_step import copy_into, on_side_stream, shapes
from sb3_taskalloc.two_stage_sac.select_stage import Decision, decode_round

if TYPE_CHECKING:
    from sb3_taskalloc.two_stage_sac.policies import TAMPolicy

#: Pick steps per round of a recorded decision. The zoo's untrained RBF policy needs up to 30 in a round (876 rounds of
#: 3 episodes, argmax and samples; 155 need more than 16), MT's up to 11: a longer team falls back to the eager loop.
DECISION_STEPS = 32

#: Eager decisions of a new shape, on a side stream, before it records (CUDA's libraries build their workspaces).
DECISION_WARMUP = 2


class FixedSteps:
    """Each round's teams decoded by ``steps`` pick steps with no host read (:func:`.decode_round`'s fixed loop);
    :attr:`unfinished` (a bool tensor) becomes true where a task was still decoding after them."""

    def __init__(self, steps: int, deterministic: bool, device: th.device) -> None:
        self.steps, self.deterministic = steps, deterministic
        self.unfinished = th.zeros((), dtype=th.bool, device=device)

    def teams(self, policy: TAMPolicy, view: ObsView, task_of: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """As :meth:`.Decoder.teams` of the argmax or of samples (:meth:`.TAMPolicy.select_round`), by fixed steps."""
        head = policy.selector.head
        st = decode_round(head, policy.select_view(view), task_of, self.deterministic, fixed_picks=True, steps=self.steps)
        self.unfinished = self.unfinished | st.active.any()
        return st.rank, st.kept()


def decide_fixed(policy: TAMPolicy, view: ObsView, deterministic: bool, steps: int) -> tuple[Decision, th.Tensor]:
    """``policy.decide(view, deterministic)`` with every round run and decoded by ``steps`` pick steps, and the flag
    of :class:`FixedSteps`: where it is false, the decision is the eager one (argmax), or a sample of the same law."""
    fixed = FixedSteps(steps, deterministic, view.pair_cost.device)
    decision = decide_preassigned(policy, view, policy.decoder if deterministic else SAMPLED, fixed=fixed)
    return decision, fixed.unfinished


class RecordedDecision:
    """One observation shape's decision recorded as a CUDA graph, on a copy of the first ``view`` (the graph's input).

    :param policy: the policy; the graph reads its parameters in place (an optimizer step or ``load_state_dict``
        updates them; new parameter tensors need a new recording, :meth:`DecisionGraph.key`)
    """

    def __init__(self, policy: TAMPolicy, view: ObsView, deterministic: bool, steps: int) -> None:
        with th.inference_mode(False):  # plain tensors, which callers in and out of inference mode may copy into
            self.view = ObsView(*(x.clone() for x in view))
        with th.inference_mode():
            for _ in range(DECISION_WARMUP):
                on_side_stream(lambda: decide_fixed(policy, self.view, deterministic, steps))
            self.graph = th.cuda.CUDAGraph()
            with th.cuda.graph(self.graph):
                self.decision, self.unfinished = decide_fixed(policy, self.view, deterministic, steps)

    def __call__(self, view: ObsView) -> Decision | None:
        """The decision of ``view`` (copied into the graph's input), or None where a team needed more steps."""
        copy_into(self.view, view)
        self.graph.replay()
        if bool(self.unfinished):  # the decision's one host read
            return None
        with th.inference_mode(False):  # plain copies: the next replay overwrites the graph's outputs
            return Decision(*(x.clone() for x in self.decision))


class DecisionGraph:
    """The policy's own decisions on CUDA (training's samples; with ``argmax`` the argmax decoder's too), each
    observation shape recorded once (:class:`RecordedDecision`) and replayed; :meth:`decide` answers None where the
    eager path decides.

    :param steps: pick steps per round (:data:`DECISION_STEPS`)
    :param argmax: record deterministic decisions too. ``cuda_graph=True`` leaves it off: one observation's decision
        of the zoo's four-round policies took longer replayed than eager on an H200 (RBF 27.6 against 25.4 ms, MT 27.1
        against 13.5), while at 1000 entities × 50 tasks it took 9.8 against 32.9 ms (docs/benchmarks.md)
    """

    def __init__(self, steps: int = DECISION_STEPS, argmax: bool = False) -> None:
        check_counts({"steps": steps})
        self.steps, self.argmax = steps, argmax
        self.recorded: dict[tuple, RecordedDecision] = {}
        self.replays = self.fallbacks = 0

    @staticmethod
    def key(policy: TAMPolicy, view: ObsView, deterministic: bool) -> tuple:
        """What a recording is bound to: the input shapes, argmax or samples, and the parameters' memory."""
        memory = tuple(p.data_ptr() for p in policy.parameters())
        return (deterministic, *shapes(view), memory)

    def decide(self, policy: TAMPolicy, view: ObsView, deterministic: bool, uniform: bool) -> Decision | None:
        """The recorded decision of ``view``, or None: not on CUDA, a deterministic decision without :attr:`argmax` or
        by a decoder of its own (a search, exact covers), the uniform warm-up, or a team that needed more than
        :attr:`steps` pick steps (counted in :attr:`fallbacks`)."""
        own = self.argmax and type(policy.decoder) is Decoder if deterministic else not uniform
        if not (view.pair_cost.is_cuda and policy.preassign and own):
            return None
        key = self.key(policy, view, deterministic)
        if key not in self.recorded:
            self.recorded[key] = RecordedDecision(policy, view, deterministic, self.steps)
        decision = self.recorded[key](view)
        if decision is None:
            self.fallbacks += 1
        else:
            self.replays += 1
        return decision
