"""Actor and critic modules of the two stages, assembled from :mod:`~sb3_taskalloc.common.torch_layers` and
:mod:`~sb3_taskalloc.common.mixers` by :class:`~sb3_taskalloc.TAMPolicy`.

Stage 1 (pre-assignment): :class:`PreAssignActor` and a :class:`TwinCritic` of mixing critics: :class:`AMIXCritic`
(per-entity scores mixed by AMIX) or :class:`GlobalCritic` (the "W/o AMIX" ablation). The critics split their work
the same way: :meth:`context` (everything that does not depend on the assignment, computed once) and :meth:`mix` (the
value of one assignment), so the losses treat them alike.

Stage 2 (select): :class:`Selector` (the pointer actor) and :class:`SelectCritic` (its twin Q-functions).
"""

from __future__ import annotations

from typing import Generic, NamedTuple, TypeVar

import torch as th
from torch import nn

from sb3_taskalloc.common.distributions import MaskedCategorical
from sb3_taskalloc.common.mixers import AMIXMixer, GlobalMixer, MixContext, TeamValue
from sb3_taskalloc.common.torch_layers import ObsView, PointerHead


class PreAssignActor(nn.Module):
    """π_i(j|s) = softmax over open tasks of h_i·g_j/√d (+ pair term): one categorical per free entity.

    :param scorer: a :class:`~sb3_taskalloc.common.torch_layers.PairScorer` (TAM) or
        :class:`~sb3_taskalloc.common.torch_layers.FlatScorer` (W/o TAM)
    :param logit_scale: κ, the logits are κ·s_ij: the inverse temperature of the policy, a constant
    """

    optimizer: th.optim.Optimizer

    def __init__(self, scorer: nn.Module, logit_scale: float = 1.0) -> None:
        super().__init__()
        self.scorer = scorer
        self.logit_scale = logit_scale

    @property
    def size_agnostic(self) -> bool:
        return bool(self.scorer.size_agnostic)

    def forward(self, view: ObsView) -> MaskedCategorical:
        scores = self.scorer(view)
        return MaskedCategorical(scores if self.logit_scale == 1.0 else scores * self.logit_scale, view.valid)


class AMIXContext(NamedTuple):
    """Action-independent part of an :class:`AMIXCritic` for a batch of states."""

    scores: th.Tensor  # (B, N, M) Q_i(s, j)
    mix: MixContext  # AMIX attention, values and hyper-bias
    view: ObsView  # the states (read by the team value with each assignment)

    def detach(self) -> AMIXContext:
        return AMIXContext(self.scores.detach(), self.mix.detach(), self.view)


class GlobalContext(NamedTuple):
    """Action-independent part of a :class:`GlobalCritic`: the states themselves (its MLP reads them with c)."""

    view: ObsView

    def detach(self) -> GlobalContext:
        return self


CriticContext = AMIXContext | GlobalContext
ContextT = TypeVar("ContextT", AMIXContext, GlobalContext)


class MixingCritic(nn.Module, Generic[ContextT]):
    """What the stage-1 critics share: Q(s, c) split into :meth:`context` (everything that does not depend on the
    assignment, computed once) and :meth:`mix` (the value of one assignment), read at the candidate sets of a decision."""

    def context(self, view: ObsView) -> ContextT:
        raise NotImplementedError

    def mix(self, ctx: ContextT, assign: th.Tensor) -> th.Tensor:
        """:param assign: (B, N, M) one-hot pre-assignment or policy probabilities; :return: (B,)"""
        raise NotImplementedError

    def forward(self, view: ObsView, assign: th.Tensor) -> th.Tensor:
        return self.mix(self.context(view), assign)


class AMIXCritic(MixingCritic[AMIXContext]):
    """Q_tot(s, c) = AMIX(Σ_j c_ij Q_i(s, j)) (+ V_team(s, c)) with per-entity scores Q_i(s, j) = o_i·q_j (+ pair term).

    :param scorer: per-entity Q scorer (TAM or flat)
    :param mixer: the AMIX mixer
    :param team: the per-task team value added to the mixed value, or None (the paper's critic)
    """

    def __init__(self, scorer: nn.Module, mixer: AMIXMixer, team: TeamValue | None = None) -> None:
        super().__init__()
        self.scorer = scorer
        self.mixer = mixer
        self.team = team

    @property
    def size_agnostic(self) -> bool:
        return bool(self.scorer.size_agnostic and self.mixer.size_agnostic)

    def context(self, view: ObsView) -> AMIXContext:
        """Everything that does not depend on the assignment (computed once, then mixed for several assignments)."""
        return AMIXContext(self.scorer(view), self.mixer.context(view), view)

    def mix(self, ctx: AMIXContext, assign: th.Tensor) -> th.Tensor:
        """:param assign: (B, N, M) one-hot pre-assignment or policy probabilities; :return: (B,)"""
        q = self.mixer.mix((ctx.scores * assign).sum(-1), ctx.mix)
        return q if self.team is None else q + self.team(ctx.view, assign)


class GlobalCritic(MixingCritic[GlobalContext]):
    """The "W/o AMIX" critic: one MLP over the flattened state and the (one-hot or expected) assignment.

    :param mixer: the global MLP
    """

    size_agnostic = False

    def __init__(self, mixer: GlobalMixer) -> None:
        super().__init__()
        self.mixer = mixer

    def context(self, view: ObsView) -> GlobalContext:
        return GlobalContext(view)

    def mix(self, ctx: GlobalContext, assign: th.Tensor) -> th.Tensor:
        """:param assign: (B, N, M) one-hot pre-assignment or policy probabilities; :return: (B,)"""
        return self.mixer(assign, ctx.view)


class TwinCritic(nn.Module):
    """``n_critics`` independent mixing critics (clipped double-Q).

    :param critics: :class:`AMIXCritic` or :class:`GlobalCritic` instances
    """

    optimizer: th.optim.Optimizer

    def __init__(self, critics: list[AMIXCritic | GlobalCritic]) -> None:
        super().__init__()
        if not critics:
            raise ValueError("TwinCritic needs at least one critic (n_critics >= 1)")
        self.q_networks = nn.ModuleList(critics)

    @property
    def size_agnostic(self) -> bool:
        return all(q.size_agnostic for q in self.q_networks)

    def forward(
        self, view: ObsView | None, assign: th.Tensor, contexts: list[CriticContext] | None = None
    ) -> tuple[th.Tensor, ...]:
        """Each critic's Q_tot of ``assign`` in ``view``, or from the states' :meth:`contexts` where given (``view`` is
        then not read)."""
        if contexts is not None:
            return self.mix(contexts, assign)
        assert view is not None
        return tuple(q(view, assign) for q in self.q_networks)

    def contexts(self, view: ObsView) -> list[CriticContext]:
        return [q.context(view) for q in self.q_networks]  # type: ignore[operator]

    def mix(self, contexts: list[CriticContext], assign: th.Tensor) -> tuple[th.Tensor, ...]:
        return tuple(q.mix(ctx, assign) for q, ctx in zip(self.q_networks, contexts, strict=True))  # type: ignore[operator]


class Selector(nn.Module):
    """The pointer actor of the select stage.

    :param head: its pointer head
    """

    optimizer: th.optim.Optimizer
    size_agnostic = True

    def __init__(self, head: PointerHead) -> None:
        super().__init__()
        self.head = head


class SelectCritic(nn.Module):
    """Twin Q-functions of the select stage, Q(s_t, i) for every candidate i (pointer form with a per-task baseline).

    :param heads: one pointer head per critic
    """

    optimizer: th.optim.Optimizer
    size_agnostic = True

    def __init__(self, heads: list[PointerHead]) -> None:
        super().__init__()
        self.heads = nn.ModuleList(heads)

    def forward(
        self, embeddings: list[th.Tensor], task_state: th.Tensor, dyn: th.Tensor, task_of: th.Tensor
    ) -> list[th.Tensor]:
        return [h(d, task_state, dyn, task_of) for h, d in zip(self.heads, embeddings, strict=True)]

    def embed(self, view: ObsView) -> list[th.Tensor]:
        return [h.embed_entities(view) for h in self.heads]  # type: ignore[operator]
