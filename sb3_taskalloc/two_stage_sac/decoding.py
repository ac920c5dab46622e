"""Decoding strategies: how a trained :class:`~sb3_taskalloc.TAMPolicy` turns its two stages into one decision at
deployment, chosen by name (as RL4CO's ``get_decoding_strategy``) and never saved among the network's parameters.

A strategy answers two questions of every pre-assign round of a decision: which task each free entity is a candidate
of (:meth:`Decoder.preassign`), and which team each task keeps from its candidates (:meth:`Decoder.teams`). Training
never uses them: its sampled decisions are the policy's own.

>>> model.set_decoder("team_search", samples=32)            # every later deterministic predict
>>> with model.decoding("exact_covers"):                   # inside the block only
...     evaluate_policy(model, env)
>>> model.predict(obs, deterministic=True, decoder="argmax")  # one call
>>> model.set_decoder(recommended_decoder("TaskAlloc/MT-v0"))  # the env's best measured (settings.RECOMMENDED_DECODERS)

Adding a strategy is one class here, registered by name with :func:`register_decoder`.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar

import numpy as np
import torch as th

from sb3_taskalloc.common.distributions import MaskedCategorical
from sb3_taskalloc.common.torch_layers import ObsView
from sb3_taskalloc.common.utils import check_counts, check_finite
from sb3_taskalloc.two_stage_sac.search import SelectSearchResult, cover_search, exact_covers, sampled_search, select_search
from sb3_taskalloc.two_stage_sac.select_stage import Decision, decode_round, env_action_of
from sb3_taskalloc.two_stage_sac.settings import RECOMMENDED_DECODERS

if TYPE_CHECKING:
    from sb3_taskalloc.two_stage_sac.graph_decide import FixedSteps
    from sb3_taskalloc.two_stage_sac.policies import TAMPolicy

DecoderT = TypeVar("DecoderT", bound=type["Decoder"])

#: name -> strategy class; :func:`get_decoding_strategy` builds one by name.
DECODERS: dict[str, type[Decoder]] = {}


def register_decoder(cls: DecoderT) -> DecoderT:
    """Class decorator: make ``cls`` available by its ``name``."""
    DECODERS[cls.name] = cls
    return cls


class Decoder:
    """The argmax at both stages: each free entity takes its most probable task, each task its pointer's argmax team.

    Subclasses override :meth:`preassign` and/or :meth:`teams`; their keyword arguments are their whole
    configuration (:attr:`config`). A strategy that samples draws from its own stream, seeded at ``seed`` when first
    used, so an evaluation is reproducible and leaves torch's global stream alone.
    """

    name: ClassVar[str] = "argmax"
    #: Whether the strategy decides by the argmax (False: it samples from the policy's distributions).
    deterministic: ClassVar[bool] = True

    def __init__(self, seed: int = 0) -> None:
        check_counts({"seed": seed}, minimum=0)
        self.seed = seed
        self._stream: th.Generator | None = None

    @property
    def config(self) -> dict[str, Any]:
        """The keyword arguments that rebuild this strategy (:func:`get_decoding_strategy`)."""
        return {k: v for k, v in vars(self).items() if not k.startswith("_")}

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.config.items())
        return f"{type(self).__name__}({args})"

    def stream(self, device: th.device) -> th.Generator:
        """The strategy's random stream on ``device``, seeded at :attr:`seed` when first used there."""
        if self._stream is None or self._stream.device != device:
            self._stream = th.Generator(device=device).manual_seed(self.seed)
        return self._stream

    def preassign(
        self, policy: TAMPolicy, view: ObsView, dist: MaskedCategorical, first_round: bool
    ) -> tuple[th.Tensor, th.Tensor | None]:
        """(B, N) the task each free entity is a candidate of (−1: none), and (B, M) tasks the round counts as tried
        besides those with candidates (None: no others)."""
        return th.where(view.assignable, dist.get_actions(self.deterministic), -1), None

    def teams(self, policy: TAMPolicy, view: ObsView, task_of: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """(B, M, N) each task's pick steps among its candidates ``task_of`` and (B, M) the tasks kept, decoded on the
        pointer's own costs (:meth:`~.TAMPolicy.select_view`)."""
        st = policy.select_round(view, task_of, self.deterministic)
        return st.rank, st.kept()

    def decide(self, policy: TAMPolicy, view: ObsView, rounds_out: list[tuple[ObsView, th.Tensor]] | None = None) -> Decision:
        """The whole decision of a pre-assigning policy: its pre-assign rounds, each with every task's team
        (:func:`decide_preassigned`)."""
        return decide_preassigned(policy, view, self, rounds_out)


register_decoder(Decoder)


@register_decoder
class SampledDecoder(Decoder):
    """Samples at both stages from the policy's own distributions, as training collects its data."""

    name = "sampled"
    deterministic = False


@register_decoder
class UniformDecoder(Decoder):
    """Uniformly random valid choices at both stages: the warm-up's exploration (``warmup_exploration="uniform"``)."""

    name = "uniform"
    deterministic = False

    def preassign(
        self, policy: TAMPolicy, view: ObsView, dist: MaskedCategorical, first_round: bool
    ) -> tuple[th.Tensor, th.Tensor | None]:
        uniform = MaskedCategorical(th.zeros_like(view.pair_cost), view.valid)
        return th.where(view.assignable, uniform.get_actions(False), -1), None

    def teams(self, policy: TAMPolicy, view: ObsView, task_of: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        st = policy.select_round(view, task_of, deterministic=False, uniform=True)
        return st.rank, st.kept()


@register_decoder
class PreassignSearchDecoder(Decoder):
    """The first round's pre-assignment is the best, by the step's profit, of the argmax and ``samples`` − 1 joint
    pre-assignments drawn from π^(1/T) (:func:`.search.sampled_search`): the sampling decoding of attention models
    for routing (implementation detail 16). The teams are the pointer's argmax."""

    name = "preassign_search"

    def __init__(self, samples: int = 32, temperature: float = 2.0, seed: int = 0) -> None:
        super().__init__(seed)
        check_counts({"samples": samples})
        check_finite({"temperature": temperature})
        self.samples, self.temperature = samples, float(temperature)

    def preassign(
        self, policy: TAMPolicy, view: ObsView, dist: MaskedCategorical, first_round: bool
    ) -> tuple[th.Tensor, th.Tensor | None]:
        if not first_round or self.samples == 1:
            return super().preassign(policy, view, dist, first_round)
        head = policy.selector.head
        stream = self.stream(view.pair_cost.device)
        found = sampled_search(dist, head, policy.select_view(view), self.samples, self.temperature, stream)
        return found.candidates, None


@register_decoder
class TeamSearchDecoder(Decoder):
    """Each task of every round takes the best, by its profit, of the pointer's argmax team and ``samples`` − 1 teams
    sampled at ``temperature`` (:func:`.search.select_search`, implementation detail 20); with ``exact`` also the exact
    most profitable cover of its candidates (:func:`.search.cover_search`, detail 21) where it is better still."""

    name = "team_search"

    def __init__(self, samples: int = 16, temperature: float = 1.0, exact: bool = False, seed: int = 0) -> None:
        super().__init__(seed)
        check_counts({"samples": samples})
        check_finite({"temperature": temperature})
        self.samples, self.temperature = samples, float(temperature)
        if not isinstance(exact, bool):
            raise ValueError(f"exact must be True or False, got {exact!r}")
        self.exact = exact

    def teams(self, policy: TAMPolicy, view: ObsView, task_of: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        head, view = policy.selector.head, policy.select_view(view)
        found = select_search(head, view, task_of, self.samples, self.temperature, self.stream(view.pair_cost.device))
        if self.exact:
            found = cover_search(head, view, task_of, against=found)
        return found.rank, found.profit > 0  # a task's profit is positive exactly where its team is kept


@register_decoder
class ExactCoversDecoder(TeamSearchDecoder):
    """Each task's team is the better of the pointer's argmax and the exact most profitable cover of its candidates
    (the per-step MILP's formulation on the task's candidate pairs; implementation detail 21)."""

    name = "exact_covers"

    def __init__(self, seed: int = 0) -> None:
        super().__init__(samples=1, exact=True, seed=seed)

    @property
    def config(self) -> dict[str, Any]:
        return {"seed": self.seed}


@register_decoder
class ExactTopDecoder(ExactCoversDecoder):
    """The pre-assignment itself from the solver, pruned by the policy: each round solves the per-step MILP's
    formulation on the pairs that join each free entity to one of its ``top`` most probable tasks (implementation
    detail 22); its teams are the cover's, each decoded by the pointer among its members. Entities outside the cover
    stay free for the next round; the round counts as tried the tasks it covers and those of the argmax's candidate
    sets.

    With ``surcharge`` σ > 0 each pair costs (1 + σ)·c in the round's solve and in weighing its teams: the opportunity
    cost of committing an entity now, which the per-step objective leaves out (an entity sent on a trip is missing from
    the tasks that appear while it travels). The measured settings (docs/learning.md, "The surcharge's size"): on RBF
    ``top=2, surcharge=0.08`` (where learned per-robot values do better: ``entity_value``), on MT ``top=10,
    surcharge=0.64`` (every pair, as the per-step MILP, whose returns it passes by 14 %).
    """

    name = "exact_top"

    def __init__(self, top: int = 1, surcharge: float = 0.0, seed: int = 0) -> None:
        super().__init__(seed)
        check_counts({"top": top})
        check_finite({"surcharge": surcharge}, minimum=0.0, inclusive=True)
        self.top, self.surcharge = top, float(surcharge)

    @property
    def config(self) -> dict[str, Any]:
        return {"top": self.top, "surcharge": self.surcharge, "seed": self.seed}

    @property
    def plain(self) -> bool:
        """Whether the round's costs are the observation's own (no surcharge), so that its teams need no second solve."""
        return self.surcharge == 0.0

    def costed(self, view: ObsView) -> ObsView:
        """The view whose pair costs the round's solve and the weighing of its teams read: ``view`` itself without a
        surcharge, else each pair's cost raised by it."""
        return view if self.plain else view._replace(pair_cost=view.pair_cost + self.surcharge * view.pair_cost)

    def preassign(
        self, policy: TAMPolicy, view: ObsView, dist: MaskedCategorical, first_round: bool
    ) -> tuple[th.Tensor, th.Tensor | None]:
        M = view.task_mask.shape[1]
        # A stable sort breaks ties between equally probable tasks toward the lower slot, as the argmax does, so its
        # first column is the argmax and top = 1 keeps the argmax's own tasks (topk's order among ties is unspecified).
        order = th.sort(dist.logits, dim=-1, descending=True, stable=True).indices
        chosen = th.zeros_like(view.valid).scatter_(-1, order[..., : min(self.top, M)], True)
        covers = exact_covers(self.costed(view), chosen & view.valid & view.assignable.unsqueeze(-1))
        argmax = th.where(view.assignable, order[..., 0], -1)
        tasks = th.arange(M, device=argmax.device).view(1, M, 1)
        return covers, (argmax.unsqueeze(1) == tasks).any(-1)

    def teams(self, policy: TAMPolicy, view: ObsView, task_of: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        head = policy.selector.head
        if self.plain and policy.select_values is None:
            # The candidates are the round's exact cover, whose every team is the most profitable of its own members, so
            # the exact cover of the candidates is the candidates themselves and is not solved again: each task keeps the
            # pointer's argmax among them (the exact cover's decode is that same decode). Only a HiGHS row stopped at its
            # node limit, unproven, may keep a member that a second solve would drop.
            found = select_search(head, view, task_of, 1, self.temperature)
            return found.rank, found.profit > 0
        # On other costs than the pointer's, the pointer's argmax team (decoded on the costs it was trained on) is weighed
        # by the round's objective against the exact cover among the candidates, which the round's solve already chose.
        costed = self.costed(view)
        base = policy.select_round(view, task_of, deterministic=True)
        members = (base.rank >= 0).float()  # (B, M, N)
        p0 = base.kept() * (view.reward - (members * costed.pair_cost.transpose(1, 2)).sum(-1))
        found = cover_search(head, costed, task_of, against=SelectSearchResult(base.rank, p0, p0), members=task_of)
        return found.rank, found.profit > 0


class DecodingMixin:
    """For an SB3 algorithm whose policy has a :attr:`decoder`: choose it by name, for every later deterministic
    decision or for one block or call."""

    policy: Any

    def set_decoder(self, decoder: str | Decoder, **config: Any) -> None:
        """Decode every later deterministic decision (``predict(deterministic=True)``, ``evaluate_policy``) by the
        strategy ``decoder`` (:mod:`~sb3_taskalloc.two_stage_sac.decoding`), e.g. ``set_decoder("team_search",
        samples=32)``. Training's sampled decisions are unaffected, and the strategy is not saved with the model."""
        self.policy.decoder = get_decoding_strategy(decoder, **config)

    @contextmanager
    def decoding(self, decoder: str | Decoder, **config: Any) -> Iterator[Decoder]:
        """:meth:`set_decoder` inside a ``with`` block only."""
        previous = self.policy.decoder
        self.set_decoder(decoder, **config)
        try:
            yield self.policy.decoder
        finally:
            self.policy.decoder = previous

    def predict(  # type: ignore[override]
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
        decoder: str | Decoder | None = None,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """SB3's ``predict``; ``decoder`` (a strategy's name or object) decodes this call's deterministic decision."""
        if decoder is None:
            return super().predict(observation, state, episode_start, deterministic)  # type: ignore[misc]
        with self.decoding(decoder):
            return super().predict(observation, state, episode_start, deterministic)  # type: ignore[misc]


def get_decoding_strategy(name: str | Decoder, **config: Any) -> Decoder:
    """The strategy ``name`` (:data:`DECODERS`) built with ``config``; a :class:`Decoder` passes through."""
    if isinstance(name, Decoder):
        if config:
            raise ValueError(f"a Decoder instance takes no further settings, got {sorted(config)}")
        return name
    if name not in DECODERS:
        raise ValueError(f"unknown decoding strategy {name!r}; choose from {sorted(DECODERS)}")
    try:
        return DECODERS[name](**config)
    except TypeError as error:
        raise ValueError(f"decoding strategy {name!r}: {error}") from None


def recommended_decoder(env_id: str) -> Decoder:
    """The best decoding measured on ``env_id`` (:data:`~sb3_taskalloc.two_stage_sac.settings.RECOMMENDED_DECODERS`),
    e.g. ``model.set_decoder(recommended_decoder("TaskAlloc/MT-v0"))``."""
    if env_id not in RECOMMENDED_DECODERS:
        raise ValueError(
            f"no decoder was measured on {env_id!r} (only on {sorted(RECOMMENDED_DECODERS)}): it decides by the argmax, "
            "or choose a strategy by name"
        )
    name, config = RECOMMENDED_DECODERS[env_id]
    return get_decoding_strategy(name, **config)


#: Training's decisions: samples at both stages, or uniformly random valid choices during a uniform warm-up.
SAMPLED, UNIFORM = get_decoding_strategy("sampled"), get_decoding_strategy("uniform")


def decide_preassigned(
    policy: TAMPolicy,
    view: ObsView,
    decoder: Decoder,
    rounds_out: list[tuple[ObsView, th.Tensor]] | None = None,
    fixed: FixedSteps | None = None,
) -> Decision:
    """Stage 1 (Algorithm 2): every free entity takes one open task (candidate sets C_j); stage 2 (Algorithm 3):
    every task decodes its team from its own candidates, all in one round, both as ``decoder`` decides. With
    ``rounds`` > 1 the entities left over pre-assign again among the tasks not tried yet (see ``rounds``); the
    decision records the first round. With ``fixed`` (a decision recorded as a CUDA graph, :mod:`.graph_decide`)
    every round runs, with no host check whether an entity is left, and ``fixed`` decodes the teams."""
    assert policy.actor is not None
    teams = decoder.teams if fixed is None else fixed.teams
    B, N, M = view.pair_cost.shape
    tasks = th.arange(M, device=view.pair_cost.device).view(1, M, 1)
    first: Decision | None = None
    env_action = th.full((B, N), M, dtype=th.long, device=view.pair_cost.device)
    for r in range(policy.rounds):
        dist = None if decoder is UNIFORM else policy.actor(view)  # the uniform warm-up needs no actor pass
        c, also_tried = decoder.preassign(policy, view, dist, first_round=r == 0)  # type: ignore[arg-type]
        if rounds_out is not None:
            rounds_out.append((view, c))
        rank, kept = teams(policy, view, c)
        candidates = c.unsqueeze(1) == tasks
        action = env_action_of(rank, kept)
        if first is None:
            first = Decision(action, candidates, rank, kept)
        env_action = th.where(action < M, action, env_action)
        if r + 1 == policy.rounds:  # no round follows: skip the next view and its device sync
            break
        tried = candidates.any(-1) if also_tried is None else candidates.any(-1) | also_tried
        view = view._replace(entity_mask=view.entity_mask & (env_action == M), task_mask=view.task_mask & ~tried)
        if fixed is None and not bool(view.assignable.any()):
            break
    assert first is not None
    return first._replace(env_action=env_action)


def decide_pooled(
    policy: TAMPolicy, view: ObsView, deterministic: bool, uniform: bool, select_view: ObsView | None = None
) -> Decision:
    """W/o Pre: tasks pick in turn (``task_order``) from one shared pool; abandoned picks return to the pool (the
    published code lost them).

    :param select_view: ``view`` on the pair costs the pointer decodes on (None: :meth:`~.TAMPolicy.select_view`'s)"""
    costed = policy.select_view(view) if select_view is None else select_view
    B, N, M = view.pair_cost.shape
    device = view.pair_cost.device
    if policy.task_order == "random":
        order = th.argsort(th.rand(B, M, device=device), dim=1)
    else:
        order = th.arange(M, device=device).expand(B, M)
    pool = view.entity_mask.clone()
    candidates = th.zeros(B, M, N, dtype=th.bool, device=device)
    rank = th.full((B, M, N), -1, dtype=th.long, device=device)
    kept = th.zeros(B, M, dtype=th.bool, device=device)
    rows = th.arange(B, device=device)
    for r in range(M):
        j = order[:, r]
        open_j = view.task_mask[rows, j]
        task_of = th.where(pool & open_j.unsqueeze(-1), j.unsqueeze(-1), -1)
        candidates[rows, j] = task_of >= 0
        st = decode_round(policy.selector.head, costed, task_of, deterministic, uniform)
        kept_r = st.kept()
        rank = th.where(st.rank >= 0, st.rank, rank)
        kept = kept | kept_r
        pool = pool & ~((st.rank >= 0) & kept_r.unsqueeze(-1)).any(1)
    return Decision(env_action_of(rank, kept), candidates, rank, kept)
