"""Policies of TwoStageSAC: the TAM pre-assign actor, twin AMIX critics and the pointer select head (DESIGN §5)."""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from typing import Any, Literal, NamedTuple

import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_taskalloc.common.distributions import MaskedCategorical, masked_pick, segment_sum
from sb3_taskalloc.common.torch_layers import (
    NEG,
    PAIR_COST,
    UNIT_COST,
    AMIXMixer,
    FlatScorer,
    GlobalMixer,
    MixContext,
    ObsView,
    PairScorer,
    PointerHead,
    parse_obs,
    symlog,
)

#: A task counts as covered (internally) when every remaining demand is at most this (the env's tolerance is larger).
COVER_TOL = 1e-5

#: Initial weights of ``TAMPolicy(heuristic_init=True)`` (implementation detail 10 of TwoStageSAC): the pre-assign
#: actor's weight on the symlog pair cost (each entity leans to its cheapest task), the pointer's weight on the symlog
#: unit cost (a task picks the candidate that covers its remaining demand at the lowest cost per unit, the greedy
#: allocator's rule), and the gain of the last layer of the task embeddings whose dot products add to both scores.
HEURISTIC_INIT: dict[str, float] = {"pair_cost": -3.0, "unit_cost": -10.0, "embedding_gain": 0.0}


class Decision(NamedTuple):
    """One two-stage decision for a batch of observations."""

    env_action: th.Tensor  # (B, N) task slot per entity, M = unassigned
    candidates: th.Tensor  # (B, M, N) bool: entity i was a candidate of task j
    pick_rank: th.Tensor  # (B, M, N) long: step at which task j picked entity i, −1 if not
    kept: th.Tensor  # (B, M) bool: task covered with positive internal profit


class SelectState:
    """State of the select stage for every task of every batch row (paper Algorithm 1, stage 2).

    Each entity takes part in the decoding of at most one task (``task_of``), so all tasks of all rows decode in
    parallel: the per-task state is the remaining demand (dropping by each pick's supply, clipped at 0), the cost
    of the picks so far and the number of picks.

    :param view: the observations
    :param task_of: (B, N) task whose candidate entity i is in this round (−1: none)
    """

    def __init__(self, view: ObsView, task_of: th.Tensor) -> None:
        B, N = task_of.shape
        M = view.task_mask.shape[1]
        self.view = view
        self.task_of = task_of
        self.slots = th.arange(M, device=task_of.device)
        self.seg = task_of.unsqueeze(1) == self.slots.view(1, M, 1)  # (B, M, N) candidates of task j
        self.avail = task_of >= 0  # (B, N) candidates not picked yet
        self.rem = view.demand.clone()
        self.cost = th.zeros(B, M, device=task_of.device)
        self.npick = th.zeros(B, M, device=task_of.device)
        self.covered = th.zeros(B, M, dtype=th.bool, device=task_of.device)
        self.rank = th.full((B, M, N), -1, dtype=th.long, device=task_of.device)  # step at which task j picked i
        self.pc_own = own_column(view.pair_cost, task_of)  # (B, N)
        self.useful = useful_supply(view, task_of, self.rem)  # shared by the choices and the pointer's features
        self.choosable = choosable(view, task_of, self.avail, self.rem, self.useful)  # (B, N)
        self.active = view.task_mask & still_winnable(view, task_of, self.choosable, self.pc_own, self.rem, self.cost)

    def features(self) -> tuple[th.Tensor, th.Tensor]:
        """Task states (B, M, K + 4) and entity dynamic features (B, N, SELECT_DYN) for the pointer heads."""
        return select_features(self.view, self.task_of, self.pc_own, self.rem, self.cost, self.npick, self.useful)

    def choice_mask(self) -> th.Tensor:
        """(B, M, N) entities task j may pick now."""
        return self.seg & self.choosable.unsqueeze(1) & self.active.unsqueeze(-1)

    def advance(self, picks: th.Tensor, valid: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """Apply one pick per task. :param picks: (B, M) entity index; :param valid: (B, M) rows that pick.
        :return: select-stage reward (−pair cost, + task reward on covering) and done flags, both (B, M)."""
        v = self.view
        vf = valid.float()
        pc = th.gather(v.pair_cost, 1, picks.unsqueeze(1)).squeeze(1)  # (B, M): pair_cost[b, picks[b, j], j]
        sup = th.gather(v.supply, 1, picks.unsqueeze(-1).expand(-1, -1, v.supply.shape[-1]))  # (B, M, K)
        rem = th.where(valid.unsqueeze(-1), (self.rem - sup).clamp_min(0.0), self.rem)
        newly = valid & (rem <= COVER_TOL).all(-1)
        reward = vf * (-pc + v.reward * newly.float())
        self.rem = rem
        self.cost = self.cost + vf * pc
        self.npick = self.npick + vf
        self.covered = self.covered | newly
        picked = (nn.functional.one_hot(picks, self.avail.shape[1]).bool() & valid.unsqueeze(-1)).any(1)
        self.avail = self.avail & ~picked
        self.useful = useful_supply(v, self.task_of, rem)
        self.choosable = choosable(v, self.task_of, self.avail, rem, self.useful)
        done = valid & (newly | ~still_winnable(v, self.task_of, self.choosable, self.pc_own, self.rem, self.cost))
        self.active = self.active & ~done
        return reward, done

    def kept(self) -> th.Tensor:
        """(B, M) tasks whose internal profit (reward if covered − Σ pair costs) is positive; others are abandoned."""
        return self.covered & (self.view.reward - self.cost > 0)


def own_column(x: th.Tensor, task_of: th.Tensor) -> th.Tensor:
    """(B, N) ``x[b, i, task_of[b, i]]``: each entity's entry for its own task (arbitrary where task_of < 0).

    :param x: (B, N, M) per entity and task
    :param task_of: (B, N) task each entity is a candidate of (−1: none)
    """
    return th.gather(x, 2, task_of.clamp_min(0).unsqueeze(-1)).squeeze(-1)


def useful_supply(view: ObsView, task_of: th.Tensor, rem: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """What each candidate would contribute to its task now: Σ_k min(s_ik, d_jk) for j = its task.

    :param task_of: (B, N) task each entity is a candidate of (−1: none)
    :param rem: (..., B, M, K) remaining demand
    :return: the useful supply (..., B, N) and the remaining demand of each entity's task (..., B, N, K)
    """
    idx = task_of.clamp_min(0).expand(*rem.shape[:-3], -1, -1)
    rem_i = th.gather(rem, -2, idx.unsqueeze(-1).expand(*idx.shape, rem.shape[-1]))
    return th.minimum(view.supply, rem_i).sum(-1), rem_i


def choosable(
    view: ObsView,
    task_of: th.Tensor,
    avail: th.Tensor,
    rem: th.Tensor,
    useful: tuple[th.Tensor, th.Tensor] | None = None,
) -> th.Tensor:
    """(..., B, N) candidates not picked yet that would cover some of their task's remaining demand: the select-stage
    choices (a candidate that covers nothing could only add cost).

    :param avail: (..., B, N) candidates not picked yet; see :func:`useful_supply` for the others
    :param useful: :func:`useful_supply` of (``task_of``, ``rem``) when already computed
    """
    return avail & ((useful or useful_supply(view, task_of, rem))[0] > COVER_TOL)


def still_winnable(
    view: ObsView, task_of: th.Tensor, choosable: th.Tensor, pc_own: th.Tensor, rem: th.Tensor, cost: th.Tensor
) -> th.Tensor:
    """Whether each uncovered task can still be kept: its choosable candidates can cover the remaining demand, and
    the cost so far plus the cheapest of them stays below the reward (covering needs at least one more pick). A task
    that cannot is abandoned at once (its decoding stops): pair costs are non-negative (DESIGN §3), so it would end
    uncovered or unprofitable anyway and the env action is the same as decoding on. Feasibility needs no per-pair
    minimum: Σ_i min(s_ik, d_k) ≥ d_k holds exactly when Σ_i s_ik ≥ d_k.

    :param task_of: (B, N) task each entity is a candidate of (−1: none)
    :param choosable: (..., B, N) the choices of :func:`choosable`
    :param pc_own: (B, N) pair cost of each entity for the task it is a candidate of
    :param rem: (..., B, M, K) remaining demand; :param cost: (..., B, M) pair costs of the picks so far
    :return: (..., B, M) bool
    """
    M = rem.shape[-2]
    seg = task_of.clamp_min(0).expand_as(choosable)
    cand = choosable & (task_of >= 0)
    supply_left = segment_sum(cand.unsqueeze(-1) * view.supply, seg, M, vector=True)  # (..., B, M, K)
    own_cost = pc_own.expand_as(cand).masked_fill(~cand, th.inf)
    cheapest = own_cost.new_full((*cand.shape[:-1], M), th.inf).scatter_reduce_(-1, seg, own_cost, "amin")  # inf: none
    return (supply_left >= rem - COVER_TOL).all(-1) & (view.reward - cost - cheapest > 0)


def select_features(
    view: ObsView,
    task_of: th.Tensor,
    pc_own: th.Tensor,
    rem: th.Tensor,
    cost: th.Tensor,
    npick: th.Tensor,
    useful: tuple[th.Tensor, th.Tensor] | None = None,
) -> tuple[th.Tensor, th.Tensor]:
    """Inputs of the pointer heads for one or many (leading dims) select-stage states.

    :param view: observations (B, ...)
    :param task_of: (B, N) task each entity is a candidate of (−1: none)
    :param pc_own: (B, N) pair cost of each entity for that task
    :param rem: (..., B, M, K) remaining demand; :param cost: (..., B, M) cost of the picks; :param npick: (..., B, M)
    :param useful: :func:`useful_supply` of (``task_of``, ``rem``) when already computed
    :return: task states (..., B, M, K + 4) and dynamic entity features (..., B, N, 7): coverage of the remaining
        demand, symlog pair cost, symlog margin m (reward − cost so far − pair cost), relu(m), waste share of the supply,
        whether the entity alone covers the remaining demand, and symlog of its unit cost (pair cost per unit of the
        remaining demand it covers): a fixed basis that the pointer weighs linearly
    """
    demand_sum = view.demand.sum(-1).clamp_min(1e-6)
    reward = view.reward.expand_as(cost)
    task_state = th.cat(
        [
            symlog(rem),
            symlog(reward).unsqueeze(-1),
            symlog(cost).unsqueeze(-1),
            symlog(npick).unsqueeze(-1),
            (rem.sum(-1) / demand_sum).unsqueeze(-1),
        ],
        dim=-1,
    )
    idx = task_of.clamp_min(0).expand(*rem.shape[:-3], -1, -1)
    useful_i, rem_i = useful or useful_supply(view, task_of, rem)
    cov = useful_i / rem_i.sum(-1).clamp_min(1e-6)
    waste = 1.0 - useful_i / view.supply.sum(-1).clamp_min(1e-6)
    margin = th.gather(reward - cost, -1, idx) - pc_own
    m = symlog(margin)
    unit_cost = symlog(pc_own / useful_i.clamp_min(1e-6))  # the greedy allocator's key: cost per unit of demand covered
    covers = (cov >= 1 - 1e-6).float()
    dyn = th.stack([cov, symlog(pc_own).expand_as(cov), m, th.relu(m), waste, covers, unit_cost], dim=-1)
    return task_state, dyn


class PreAssignActor(nn.Module):
    """π_i(j|s) = softmax over open tasks of h_i·g_j/√d (+ pair term): one categorical per free entity.

    :param scorer: a :class:`PairScorer` (TAM) or :class:`FlatScorer` (W/o TAM)
    """

    optimizer: th.optim.Optimizer

    def __init__(self, scorer: nn.Module) -> None:
        super().__init__()
        self.scorer = scorer

    def forward(self, view: ObsView) -> MaskedCategorical:
        return MaskedCategorical(self.scorer(view), view.valid)


class CriticContext(NamedTuple):
    """Action-independent part of a :class:`MixingCritic` for a batch of states: Q_i(s, j) and the mixer's context."""

    view: ObsView
    scores: th.Tensor | None  # (B, N, M) Q_i(s, j) (None with the global mixer)
    mix: MixContext | None  # AMIX attention, values and hyper-bias (None with the global mixer)

    def detach(self) -> CriticContext:
        return CriticContext(
            self.view, None if self.scores is None else self.scores.detach(), None if self.mix is None else self.mix.detach()
        )


class MixingCritic(nn.Module):
    """Q_tot(s, c) = AMIX(Σ_j c_ij Q_i(s, j)) with Q_i(s, j) = o_i·q_j (+ pair term), or the global MLP (W/o AMIX).

    :param scorer: per-entity Q scorer (None with the global mixer)
    :param mixer: :class:`AMIXMixer` or :class:`GlobalMixer`
    """

    def __init__(self, scorer: nn.Module | None, mixer: nn.Module) -> None:
        super().__init__()
        self.scorer = scorer
        self.mixer = mixer

    def context(self, view: ObsView) -> CriticContext:
        """Everything that does not depend on the assignment (computed once, then mixed for several assignments)."""
        if self.scorer is None:
            return CriticContext(view, None, None)
        return CriticContext(view, self.scorer(view), self.mixer.context(view))  # type: ignore[operator]

    def mix(self, ctx: CriticContext, assign: th.Tensor) -> th.Tensor:
        """:param assign: (B, N, M) one-hot pre-assignment or policy probabilities; :return: (B,)"""
        if ctx.scores is None:
            return self.mixer(assign, ctx.view)
        return self.mixer.mix((ctx.scores * assign).sum(-1), ctx.mix)  # type: ignore[operator]

    def forward(self, view: ObsView, assign: th.Tensor) -> th.Tensor:
        """:param assign: (B, N, M) one-hot pre-assignment or policy probabilities; :return: (B,)"""
        return self.mix(self.context(view), assign)


class TwinCritic(nn.Module):
    """``n_critics`` independent :class:`MixingCritic` (clipped double-Q)."""

    optimizer: th.optim.Optimizer

    def __init__(self, critics: list[MixingCritic]) -> None:
        super().__init__()
        self.q_networks = nn.ModuleList(critics)

    def forward(self, view: ObsView, assign: th.Tensor) -> tuple[th.Tensor, ...]:
        return tuple(q(view, assign) for q in self.q_networks)

    def contexts(self, view: ObsView) -> list[CriticContext]:
        return [q.context(view) for q in self.q_networks]  # type: ignore[operator]

    def mix(self, contexts: list[CriticContext], assign: th.Tensor) -> tuple[th.Tensor, ...]:
        return tuple(q.mix(ctx, assign) for q, ctx in zip(self.q_networks, contexts, strict=True))  # type: ignore[operator]


class SelectCritic(nn.Module):
    """Twin Q-functions of the select stage, Q(s_t, i) for every candidate i (pointer form with ReLU)."""

    optimizer: th.optim.Optimizer

    def __init__(self, heads: list[PointerHead]) -> None:
        super().__init__()
        self.heads = nn.ModuleList(heads)

    def forward(
        self, embeddings: list[th.Tensor], task_state: th.Tensor, dyn: th.Tensor, task_of: th.Tensor
    ) -> list[th.Tensor]:
        return [h(d, task_state, dyn, task_of) for h, d in zip(self.heads, embeddings, strict=True)]

    def embed(self, view: ObsView) -> list[th.Tensor]:
        return [h.embed_entities(view) for h in self.heads]  # type: ignore[operator]


class Selector(nn.Module):
    """The pointer actor of the select stage."""

    optimizer: th.optim.Optimizer

    def __init__(self, head: PointerHead) -> None:
        super().__init__()
        self.head = head


class TAMPolicy(BasePolicy):
    """Policy of :class:`~sb3_taskalloc.TwoStageSAC`: TAM pre-assign actor, twin TAM critics mixed by AMIX, and the
    pointer select head with its twin critic. Size-agnostic in the number of entities and tasks (with the defaults).

    :param observation_space: Dict observation space of a ``TaskAlloc`` env
    :param action_space: MultiDiscrete([M + 1] * N)
    :param lr_schedule: learning rate schedule
    :param hidden_dim: width d of every embedding and hidden layer (paper: 64)
    :param n_attention_layers: self-attention blocks in the TAM encoders (0: MLP embeddings, as the paper)
    :param pair_features: add a learned linear term of the fixed pair basis (pair cost, coverage, margin) to the TAM scores
    :param preassign: two stages (True) or the "W/o Pre" ablation: tasks pick from one shared pool
    :param task_order: order of the tasks without pre-assignment: ``"sequential"`` (slot order) or ``"random"``
    :param encoder: ``"tam"`` (size-agnostic attention module) or ``"mlp"`` (the "W/o TAM" ablation, size-specific)
    :param mixer: ``"amix"`` or ``"global"`` (the "W/o AMIX" ablation: one MLP over the flattened state and c)
    :param monotonic_mixer: QMIX-style non-negative mixing weights
    :param hyper_bias: state-dependent AMIX bias
    :param n_critics: number of critics (clipped double-Q)
    :param heuristic_init: start the pre-assign actor and the pointer at cost-greedy rules (:data:`HEURISTIC_INIT`):
        their linear read-outs weigh only the pair cost and the unit cost, and the dot-product terms start near 0;
        learning then corrects the rules. ``False``: PyTorch's default initialisation (the paper)
    :param activation_fn: activation of the MLPs (paper: ReLU)
    :param optimizer_class: optimizer of every network
    :param optimizer_kwargs: extra optimizer arguments
    """

    actor: PreAssignActor | None
    critic: TwinCritic | None
    critic_target: TwinCritic | None
    actor_prior: PreAssignActor | None
    selector_prior: Selector

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.MultiDiscrete,
        lr_schedule: Schedule,
        hidden_dim: int = 64,
        n_attention_layers: int = 0,
        pair_features: bool = True,
        preassign: bool = True,
        task_order: Literal["sequential", "random"] = "sequential",
        encoder: Literal["tam", "mlp"] = "tam",
        mixer: Literal["amix", "global"] = "amix",
        monotonic_mixer: bool = False,
        hyper_bias: bool = True,
        n_critics: int = 2,
        heuristic_init: bool = True,
        activation_fn: type[nn.Module] = nn.ReLU,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(
            observation_space,
            action_space,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            normalize_images=False,
        )
        check_spaces(observation_space, action_space)
        if task_order not in ("sequential", "random"):
            raise ValueError(f"task_order must be 'sequential' or 'random', got {task_order!r}")
        if encoder not in ("tam", "mlp"):
            raise ValueError(f"encoder must be 'tam' or 'mlp', got {encoder!r}")
        if mixer not in ("amix", "global"):
            raise ValueError(f"mixer must be 'amix' or 'global', got {mixer!r}")
        self.hidden_dim = hidden_dim
        self.n_attention_layers = n_attention_layers
        self.pair_features = pair_features
        self.preassign = preassign
        self.task_order = task_order
        self.encoder = encoder
        self.mixer = mixer
        self.monotonic_mixer = monotonic_mixer
        self.hyper_bias = hyper_bias
        self.n_critics = n_critics
        self.heuristic_init = heuristic_init
        self.activation_fn = activation_fn
        self._build(lr_schedule)

    # ------------------------------------------------------------------ building

    @property
    def dims(self) -> tuple[int, int, int, int, int]:
        """(N, M, Fe, Ft, K) of the observation space."""
        obs = self.observation_space
        N, Fe = obs["entity_features"].shape  # type: ignore[index]
        M, Ft = obs["task_features"].shape  # type: ignore[index]
        K = obs["entity_supply"].shape[1]  # type: ignore[index]
        return N, M, Fe, Ft, K

    @property
    def size_agnostic(self) -> bool:
        """Whether the networks accept any number of entities and tasks (TAM encoder and AMIX mixer)."""
        return not self.preassign or (self.encoder == "tam" and self.mixer == "amix")

    def _scorer(self, scale: float) -> nn.Module:
        N, M, Fe, Ft, _ = self.dims
        if self.encoder == "mlp":
            return FlatScorer(N, M, Fe, Ft, self.hidden_dim, self.activation_fn)
        return PairScorer(Fe, Ft, self.hidden_dim, scale, self.pair_features, self.n_attention_layers, self.activation_fn)

    def _make_critic(self) -> TwinCritic:
        N, M, Fe, Ft, _ = self.dims
        critics = []
        for _ in range(self.n_critics):
            if self.mixer == "global":
                critics.append(MixingCritic(None, GlobalMixer(N, M, Fe, Ft, self.hidden_dim, self.activation_fn)))
            else:
                mixer = AMIXMixer(Fe, Ft, self.hidden_dim, self.monotonic_mixer, self.hyper_bias, self.activation_fn)
                critics.append(MixingCritic(self._scorer(scale=1.0), mixer))  # critics unscaled (reference spec B20)
        return TwinCritic(critics)

    def _build(self, lr_schedule: Schedule) -> None:
        _, _, Fe, _, K = self.dims
        lr = lr_schedule(1)
        if self.preassign:
            self.actor = PreAssignActor(self._scorer(scale=math.sqrt(self.hidden_dim)))
            self.actor.optimizer = self._make_optimizer(self.actor, lr)
            self.critic = self._make_critic()
            self.critic.optimizer = self._make_optimizer(self.critic, lr)
            self.critic_target = self._make_critic()
            self.critic_target.load_state_dict(self.critic.state_dict())
            self.critic_target.train(False)
        else:
            self.actor = self.critic = self.critic_target = None
        self.selector = Selector(PointerHead(Fe, K, self.hidden_dim, self.activation_fn))
        self.selector.optimizer = self._make_optimizer(self.selector, lr)

        def make_heads() -> list[PointerHead]:
            return [PointerHead(Fe, K, self.hidden_dim, self.activation_fn, state_value=True) for _ in range(self.n_critics)]

        self.select_critic = SelectCritic(make_heads())
        self.select_critic.optimizer = self._make_optimizer(self.select_critic, lr)
        self.select_critic_target = SelectCritic(make_heads())
        self.select_critic_target.load_state_dict(self.select_critic.state_dict())
        self.select_critic_target.train(False)
        if self.heuristic_init:
            self._init_heuristic()
        # Frozen copies of the initial actors: the reference π₀ of TwoStageSAC's prior term (implementation detail 12).
        self.actor_prior = copy.deepcopy(self.actor).requires_grad_(False).train(False) if self.actor is not None else None
        self.selector_prior = copy.deepcopy(self.selector).requires_grad_(False).train(False)
        for prior in (self.actor_prior, self.selector_prior):
            if prior is not None and hasattr(prior, "optimizer"):
                del prior.optimizer
        self._freeze_priors()

    def _freeze_priors(self) -> None:
        """Let the frozen initial actors skip the dot products that their weights make identically 0."""
        if self.actor_prior is not None and isinstance(self.actor_prior.scorer, PairScorer):
            self.actor_prior.scorer.freeze()
        self.selector_prior.head.freeze()

    def _make_optimizer(self, module: nn.Module, lr: float) -> th.optim.Optimizer:
        """``optimizer_class(module.parameters(), lr, **optimizer_kwargs)``; Adam and AdamW default to their fused
        implementation (one kernel for all parameters: about 6× faster per step on a CPU thread than the per-tensor
        loop) unless ``optimizer_kwargs`` chooses an implementation."""
        kwargs = dict(self.optimizer_kwargs)
        if self.optimizer_class in (th.optim.Adam, th.optim.AdamW) and not {"fused", "foreach"} & set(kwargs):
            kwargs["fused"] = True
        return self.optimizer_class(module.parameters(), lr=lr, **kwargs)  # type: ignore[call-arg]

    @th.no_grad()
    def _init_heuristic(self) -> None:
        """Initialise the actors at the cost-greedy rules of :data:`HEURISTIC_INIT` (critics keep the default init)."""
        gain = HEURISTIC_INIT["embedding_gain"]
        scorer = self.actor.scorer if self.actor is not None else None
        if isinstance(scorer, PairScorer) and scorer.pair is not None:
            scorer.pair.weight.zero_()
            scorer.pair.weight[0, PAIR_COST] = HEURISTIC_INIT["pair_cost"]
            scorer.pair.bias.zero_()
            _scale_last_layer(scorer.encoder.f_g, gain)
        head = self.selector.head
        head.dyn.weight.zero_()
        head.dyn.weight[0, UNIT_COST] = HEURISTIC_INIT["unit_cost"]
        head.dyn.bias.zero_()
        _scale_last_layer(head.task, gain)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            dict(
                lr_schedule=self._dummy_schedule,  # type: ignore[arg-type]
                hidden_dim=self.hidden_dim,
                n_attention_layers=self.n_attention_layers,
                pair_features=self.pair_features,
                preassign=self.preassign,
                task_order=self.task_order,
                encoder=self.encoder,
                mixer=self.mixer,
                monotonic_mixer=self.monotonic_mixer,
                hyper_bias=self.hyper_bias,
                n_critics=self.n_critics,
                heuristic_init=self.heuristic_init,
                activation_fn=self.activation_fn,
                optimizer_class=self.optimizer_class,
                optimizer_kwargs=self.optimizer_kwargs,
            )
        )
        return data

    def load_state_dict(self, state_dict: Mapping[str, Any], strict: bool = True, assign: bool = False) -> Any:
        """As :meth:`torch.nn.Module.load_state_dict`; a state saved without the frozen initial actors (older models)
        takes its actors as their reference."""
        state = dict(state_dict)
        for prior, source in (("actor_prior.", "actor."), ("selector_prior.", "selector.")):
            if not any(k.startswith(prior) for k in state):
                state.update({prior + k[len(source) :]: v for k, v in state_dict.items() if k.startswith(source)})
        result = super().load_state_dict(state, strict, assign)
        self._freeze_priors()
        return result

    def set_training_mode(self, mode: bool) -> None:
        """Train/eval mode of the online networks (targets stay in eval mode); a no-op when unchanged, since SB3's
        ``predict`` calls it on every decision."""
        if getattr(self, "_mode", None) == mode:
            return
        for module in (self.actor, self.critic, self.selector, self.select_critic):
            if module is not None:
                module.train(mode)
        self.training = mode
        self._mode = mode

    # ------------------------------------------------------------------ acting

    def parse(self, obs: PyTorchObs) -> ObsView:
        assert isinstance(obs, dict), "TAMPolicy needs the Dict observations of a TaskAlloc env"
        return parse_obs(obs)

    def select_round(self, view: ObsView, task_of: th.Tensor, deterministic: bool, uniform: bool = False) -> SelectState:
        """Decode the teams of every task of one round in parallel (one pick per task per step)."""
        st = SelectState(view, task_of)
        B, _, N = st.seg.shape
        d = None if uniform else self.selector.head.embed_entities(view)
        for t in range(N):
            if not bool(st.active.any()):
                break
            mask = st.choice_mask()
            if d is None:
                logits = th.zeros(B, N, device=task_of.device)
            else:
                task_state, dyn = st.features()
                logits = self.selector.head(d, task_state, dyn, task_of)
            picks = masked_pick(logits.unsqueeze(1).masked_fill(~mask, NEG), deterministic)  # (B, M)
            valid = st.active.clone()
            old = th.gather(st.rank, 2, picks.unsqueeze(-1)).squeeze(-1)
            st.rank.scatter_(2, picks.unsqueeze(-1), th.where(valid, t, old).unsqueeze(-1))
            st.advance(picks, valid)
        return st

    def decide(self, view: ObsView, deterministic: bool = False, uniform: bool = False) -> Decision:
        """Both stages on a batch of observations.

        :param view: parsed observations
        :param deterministic: argmax at both stages (else sample)
        :param uniform: uniform random choices at both stages (warm-up exploration)
        """
        B, N = view.entity_mask.shape
        M = view.task_mask.shape[1]
        device = view.entity_mask.device
        slots = th.arange(M, device=device).view(1, M, 1)
        if self.preassign:
            # Stage 1: every free entity samples one open task (candidate sets C_j).
            assert self.actor is not None
            dist = MaskedCategorical(th.zeros(B, N, M, device=device), view.valid) if uniform else self.actor(view)
            c = th.where(view.assignable, dist.get_actions(deterministic), -1)
            st = self.select_round(view, c, deterministic, uniform)
            candidates = c.unsqueeze(1) == slots
            rank, kept = st.rank, st.kept()
        else:
            # W/o Pre: tasks pick in turn from one shared pool; abandoned picks return to the pool (B15 fixed).
            if self.task_order == "random":
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
                st = self.select_round(view, task_of, deterministic, uniform)
                kept_r = st.kept()
                rank = th.where(st.rank >= 0, st.rank, rank)
                kept = kept | kept_r
                pool = pool & ~((st.rank >= 0) & kept_r.unsqueeze(-1)).any(1)
        return Decision(env_action_of(rank, kept), candidates, rank, kept)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        with th.inference_mode():  # cheaper than SB3's no_grad for the sequential decoding
            return self.decide(self.parse(observation), deterministic).env_action

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(obs, deterministic)


def _scale_last_layer(net: nn.Sequential, gain: float) -> None:
    last = net[-1]
    assert isinstance(last, nn.Linear)
    last.weight.mul_(gain)
    last.bias.mul_(gain)


def env_action_of(rank: th.Tensor, kept: th.Tensor) -> th.Tensor:
    """(B, N) env action from the pick ranks and kept tasks: an entity goes to the kept task that picked it, else
    "unassigned" (M)."""
    M = rank.shape[1]
    assigned = (rank >= 0) & kept.unsqueeze(-1)  # (B, M, N)
    task = assigned.float().argmax(1)
    return th.where(assigned.any(1), task, th.full_like(task, M))


def check_spaces(observation_space: spaces.Space, action_space: spaces.Space) -> None:
    """Raise a clear error unless the spaces follow the TaskAlloc contract (DESIGN §3)."""
    keys = {
        "entity_features",
        "task_features",
        "entity_supply",
        "task_demand",
        "task_reward",
        "pair_cost",
        "entity_mask",
        "task_mask",
    }
    if not isinstance(observation_space, spaces.Dict) or not keys <= set(observation_space.spaces):
        raise ValueError(
            f"TAMPolicy needs a TaskAlloc Dict observation space with keys {sorted(keys)}, got {observation_space}"
        )
    N = observation_space["entity_mask"].shape[0]  # type: ignore[index]
    M = observation_space["task_mask"].shape[0]  # type: ignore[index]
    if (
        not isinstance(action_space, spaces.MultiDiscrete)
        or action_space.shape != (N,)
        or not (action_space.nvec == M + 1).all()
    ):
        raise ValueError(
            f"TAMPolicy needs MultiDiscrete([{M + 1}] * {N}) actions (M + 1 choices per entity), got {action_space}"
        )
