"""Policies of TwoStageSAC."""

from __future__ import annotations

import copy
import inspect
import math
from typing import Any, Literal

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from torch import nn

from sb3_taskalloc.common.policies import PreAssignActor, SelectCritic, Selector, TwinCritic
from sb3_taskalloc.common.spaces import check_observation, check_spaces
from sb3_taskalloc.common.torch_layers import (
    PAIR_FEATURE_NAMES,
    UNIT_COST,
    ObsView,
    PairScorer,
    PointerHead,
    parse_obs,
)
from sb3_taskalloc.common.utils import check_bools, check_choices, check_counts, check_finite, settings_over
from sb3_taskalloc.two_stage_sac.components import ENCODERS, MIXERS
from sb3_taskalloc.two_stage_sac.decoding import (
    SAMPLED,
    UNIFORM,
    Decoder,
    decide_pooled,
    get_decoding_strategy,
)
from sb3_taskalloc.two_stage_sac.entity_values import SelectValues
from sb3_taskalloc.two_stage_sac.graph_decide import DecisionGraph
from sb3_taskalloc.two_stage_sac.select_stage import Decision, SelectState, decode_round

#: Initial weights of ``TAMPolicy(heuristic_init=True)`` (implementation detail 10 of :mod:`sb3_taskalloc.two_stage_sac`):
#: the pre-assign actor's weight on the symlog pair cost (each entity leans to its cheapest task), the pointer's weight
#: on the symlog unit cost (a task picks the candidate that covers its remaining demand at the lowest cost per unit, the
#: greedy allocator's rule), and the gain of the last layer of the task embeddings whose dot products add to both scores.
HEURISTIC_INIT: dict[str, float] = {"pair_cost": -3.0, "unit_cost": -10.0, "embedding_gain": 0.0}

#: Default (κ, κ_s) of a rule-initialised policy (implementation detail 10): sampled decisions stay near the rule's argmax.
RULE_LOGIT_SCALES = (100.0, 10.0)

#: Settings of TAMPolicy's ``mixer_kwargs`` and their defaults (the AMIX critic; the "global" mixer ignores them).
MIXER_DEFAULTS: dict[str, bool] = {"monotonic": False, "hyper_bias": True, "team_value": True}


def check_rule_weights(rule_weights: dict[str, float] | None, heuristic_init: bool) -> dict[str, float]:
    """``rule_weights`` as a dict, with a clear error for an unknown pair feature, a weight that is no finite number,
    or weights without ``heuristic_init`` (whose rule they set)."""
    weights = dict(rule_weights or {})
    if not weights:
        return weights
    unknown = sorted(set(weights) - set(PAIR_FEATURE_NAMES))
    if unknown:
        raise ValueError(f"rule_weights: unknown pair features {unknown}; choose from {list(PAIR_FEATURE_NAMES)}")
    if not heuristic_init:
        raise ValueError("rule_weights set the initial rule of heuristic_init=True; got heuristic_init=False")
    check_finite({f"rule_weights[{k!r}]": v for k, v in weights.items()}, minimum=-math.inf)
    return weights


def starts_at_rule(policy_kwargs: dict[str, Any]) -> bool:
    """Whether ``TAMPolicy(**policy_kwargs)``'s pre-assign actor starts at the cost-greedy rule (:data:`HEURISTIC_INIT`):
    with ``heuristic_init``, pre-assignment and the TAM encoder's pair read-out; otherwise it starts at random weights
    (the paper's configuration, the "W/o TAM" ablation) or there is no pre-assign actor ("W/o Pre").

    :param policy_kwargs: TAMPolicy keywords; those left out take TAMPolicy's defaults
    """
    kwargs = {**_RULE_DEFAULTS, **{k: v for k, v in policy_kwargs.items() if k in _RULE_DEFAULTS}}
    return bool(kwargs["heuristic_init"] and kwargs["preassign"] and kwargs["encoder"] == "tam" and kwargs["pair_features"])


class TAMPolicy(BasePolicy):
    """Policy of :class:`~sb3_taskalloc.TwoStageSAC`: TAM pre-assign actor, twin TAM critics mixed by AMIX, and the
    pointer select head with its twin critic. Size-agnostic in the number of entities and tasks (with the defaults).

    The components are chosen by name: ``encoder`` picks the scorer of the actor and of each per-entity critic
    (:data:`ENCODERS`), ``mixer`` the stage-1 critic (:data:`MIXERS`), ``preassign`` the decision scheme. Each component
    declares whether it is ``size_agnostic``; :attr:`size_agnostic` combines them.

    :param observation_space: Dict observation space of a ``TaskAlloc`` env
    :param action_space: MultiDiscrete([M + 1] * N)
    :param lr_schedule: learning rate schedule
    :param hidden_dim: width d of every embedding and hidden layer (paper: 64)
    :param n_attention_layers: self-attention blocks in the TAM encoders (0: MLP embeddings, as the paper)
    :param pair_features: add a learned linear term of the fixed pair basis (pair cost, coverage, margin) to the TAM scores
    :param preassign: two stages (True) or the "W/o Pre" ablation: tasks pick from one shared pool
    :param task_order: order of the tasks without pre-assignment: ``"sequential"`` (slot order, the default) or
        ``"random"``; only with ``preassign=False``
    :param encoder: ``"tam"`` (size-agnostic attention module) or ``"mlp"`` (the "W/o TAM" ablation, size-specific)
    :param mixer: ``"amix"`` (the paper's) or ``"global"`` (the "W/o AMIX" ablation: one MLP over the flattened state
        and c)
    :param mixer_kwargs: settings of the AMIX critic over :data:`MIXER_DEFAULTS`: ``monotonic`` (QMIX-style weights),
        ``hyper_bias`` (a state-dependent bias), ``team_value`` (implementation detail 1; ``False``: the paper's critic)
    :param logit_scale: κ, the pre-assign actor's logits are κ times its scores (its inverse temperature; the paper's
        κ = 1; implementation detail 10); ``None``: 100 where the actor starts at the rule, else 1
    :param select_logit_scale: κ_s, the same for the pointer actor; ``None``: 10 with ``heuristic_init``, else 1
    :param rounds: pre-assign rounds per decision (implementation detail 15; the paper's 1): the entities the pointer
        did not pick pre-assign again among the open tasks not tried yet; ignored without pre-assignment
    :param n_critics: number of critics (clipped double-Q)
    :param heuristic_init: start the pre-assign actor and the pointer at cost-greedy rules (:data:`HEURISTIC_INIT`,
        implementation detail 10); ``False``: PyTorch's default initialisation (the paper)
    :param select_values: what committing an entity gives up, in the pointer's pair costs: each entity's learned
        future value ``{"theta": (θ_free, θ_τ, θ_e), "grid_size": 7}`` (grid envs with Manhattan travel) and/or a
        uniform ``{"surcharge": σ}`` (:class:`~.entity_values.SelectValues`): the select stage decodes, trains and is
        distilled on c_ij (1 + σ) + v_ij; None: on the observation's costs
    :param rule_weights: with ``heuristic_init``, the pre-assign rule's weights on the fixed pair features by name
        (:data:`~sb3_taskalloc.common.torch_layers.PAIR_FEATURE_NAMES`) over ``{"pair_cost": -3.0}``, e.g.
        ``{"margin": 3.0}`` (MT's zoo config); ignored by policies without the pre-assign pair read-out
    :param activation_fn: activation of the MLPs (paper: ReLU)
    :param optimizer_class: optimizer of every network
    :param optimizer_kwargs: extra optimizer arguments

    How a deterministic decision is decoded (the argmax, a search, exact covers) is no parameter of the network: see
    :attr:`decoder` and :mod:`~sb3_taskalloc.two_stage_sac.decoding`.
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
        task_order: Literal["sequential", "random"] | None = None,
        encoder: Literal["tam", "mlp"] = "tam",
        mixer: Literal["amix", "global"] = "amix",
        mixer_kwargs: dict[str, bool] | None = None,
        logit_scale: float | None = None,
        select_logit_scale: float | None = None,
        n_critics: int = 2,
        rounds: int = 1,
        heuristic_init: bool = True,
        rule_weights: dict[str, float] | None = None,
        select_values: dict[str, Any] | None = None,
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
        if preassign and task_order is not None:
            raise ValueError(
                f"task_order={task_order!r} applies only without pre-assignment (preassign=False): with pre-assignment "
                "every task decodes its own candidates in parallel, in no order"
            )
        task_order = task_order or "sequential"
        choices = {"task_order": (task_order, ("sequential", "random")), "encoder": (encoder, tuple(ENCODERS))}
        check_choices({**choices, "mixer": (mixer, tuple(MIXERS))})
        check_counts(dict(hidden_dim=hidden_dim, n_critics=n_critics, rounds=rounds))
        check_counts(dict(n_attention_layers=n_attention_layers), minimum=0)
        if not (isinstance(activation_fn, type) and issubclass(activation_fn, nn.Module)):
            raise ValueError(f"activation_fn must be a torch.nn.Module class such as nn.ReLU, got {activation_fn!r}")
        check_bools(dict(pair_features=pair_features, preassign=preassign, heuristic_init=heuristic_init))
        self.mixer_kwargs = settings_over("mixer_kwargs", mixer_kwargs, MIXER_DEFAULTS)
        check_bools({f"mixer_kwargs[{k!r}]": v for k, v in self.mixer_kwargs.items()})
        self.hidden_dim = hidden_dim
        self.n_attention_layers = n_attention_layers
        self.pair_features = pair_features
        self.preassign = preassign
        self.task_order = task_order
        self.encoder = encoder
        self.mixer = mixer
        #: Whether the pre-assign actor starts at the cost-greedy rule (_init_heuristic) rather than at random weights.
        self.preassign_rule = starts_at_rule(
            dict(heuristic_init=heuristic_init, preassign=preassign, encoder=encoder, pair_features=pair_features)
        )
        if logit_scale is None:
            logit_scale = RULE_LOGIT_SCALES[0] if self.preassign_rule else 1.0
        if select_logit_scale is None:
            select_logit_scale = RULE_LOGIT_SCALES[1] if heuristic_init else 1.0
        check_finite({"logit_scale": logit_scale, "select_logit_scale": select_logit_scale})
        self.logit_scale = float(logit_scale)
        self.select_logit_scale = float(select_logit_scale)
        self.n_critics = n_critics
        self.rounds = rounds
        #: How deterministic decisions are decoded (:mod:`.decoding`); not saved among the constructor parameters.
        self.decoder: Decoder = get_decoding_strategy("argmax")
        #: Its own decisions recorded as CUDA graphs (:mod:`.graph_decide`), which ``TwoStageSAC(cuda_graph=True)`` sets.
        self.decision_graph: DecisionGraph | None = None
        self.heuristic_init = heuristic_init
        self.rule_weights = check_rule_weights(rule_weights, heuristic_init)
        self.select_values = SelectValues.of(select_values)
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
        """Whether every network accepts any number of entities and tasks (read by ``TwoStageSAC.load(env=...)``)."""
        modules = (self.actor, self.critic, self.selector, self.select_critic)
        return all(m.size_agnostic for m in modules if m is not None)

    def check_transfer(self, observation_space: spaces.Dict) -> None:
        """Raise a clear error unless this policy can run on ``observation_space`` (another entity or task count)."""
        old = self.observation_space
        for key in ("entity_features", "task_features", "entity_supply"):
            new_f, old_f = observation_space[key].shape[-1], old[key].shape[-1]  # type: ignore[index]
            if new_f != old_f:
                raise ValueError(
                    f"the env's {key} has {new_f} features per row but the model was trained with {old_f}: it belongs "
                    "to another family of environments"
                )
        new_size = (observation_space["entity_mask"].shape[0], observation_space["task_mask"].shape[0])  # type: ignore[index]
        old_size = (old["entity_mask"].shape[0], old["task_mask"].shape[0])  # type: ignore[index]
        if new_size != old_size and not self.size_agnostic:
            specific = [
                f"{k}={v!r}" for k, v in (("encoder", self.encoder), ("mixer", self.mixer)) if v not in ("tam", "amix")
            ]
            raise ValueError(
                f"this model's policy is size-specific ({', '.join(specific)}): it cannot run on an env with {new_size[0]} "
                f"entities × {new_size[1]} tasks; it was trained with {old_size[0]} × {old_size[1]}. Use the TAM encoder "
                "and AMIX mixer to transfer"
            )

    def _scorer(self, scale: float) -> nn.Module:
        return ENCODERS[self.encoder](self, scale)

    def _make_critic(self) -> TwinCritic:
        return TwinCritic([MIXERS[self.mixer](self) for _ in range(self.n_critics)])

    def _build(self, lr_schedule: Schedule) -> None:
        _, _, Fe, _, K = self.dims
        lr = lr_schedule(1)
        self.actor = self.critic = self.critic_target = None
        if self.preassign:
            self.actor = PreAssignActor(self._scorer(scale=math.sqrt(self.hidden_dim)), self.logit_scale)
            self.actor.optimizer = self._make_optimizer(self.actor, lr)
            self.critic = self._make_critic()
            self.critic.optimizer = self._make_optimizer(self.critic, lr)
            self.critic_target = self._make_critic()
            self.critic_target.load_state_dict(self.critic.state_dict())
            self.critic_target.train(False)
        self.selector = Selector(PointerHead(Fe, K, self.hidden_dim, self.activation_fn, logit_scale=self.select_logit_scale))
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
        self.actor_prior = _frozen_copy(self.actor) if self.actor is not None else None
        self.selector_prior = _frozen_copy(self.selector)
        self._freeze_priors()

    def _freeze_priors(self) -> None:
        """Let the frozen initial actors skip the dot products that their weights make identically 0."""
        if self.actor_prior is not None and isinstance(self.actor_prior.scorer, PairScorer):
            self.actor_prior.scorer.freeze()
        self.selector_prior.head.freeze()

    def _make_optimizer(self, module: nn.Module, lr: float) -> th.optim.Optimizer:
        """``optimizer_class(module.parameters(), lr, **optimizer_kwargs)``; Adam and AdamW default to their fused
        implementation (one kernel for all parameters, about 6× faster per step on a CPU thread than the per-tensor
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
            for name, weight in {"pair_cost": HEURISTIC_INIT["pair_cost"], **self.rule_weights}.items():
                scorer.pair.weight[0, PAIR_FEATURE_NAMES.index(name)] = weight
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
                task_order=None if self.preassign else self.task_order,
                encoder=self.encoder,
                mixer=self.mixer,
                mixer_kwargs=dict(self.mixer_kwargs),
                logit_scale=self.logit_scale,
                select_logit_scale=self.select_logit_scale,
                n_critics=self.n_critics,
                rounds=self.rounds,
                heuristic_init=self.heuristic_init,
                rule_weights=self.rule_weights or None,
                select_values=None if self.select_values is None else self.select_values.config,
                activation_fn=self.activation_fn,
                optimizer_class=self.optimizer_class,
                optimizer_kwargs=self.optimizer_kwargs,
            )
        )
        return data

    def load_state_dict(self, state_dict: Any, strict: bool = True, assign: bool = False) -> Any:
        """As :meth:`torch.nn.Module.load_state_dict`; the frozen initial actors then re-check which dot products their
        loaded weights make identically 0."""
        result = super().load_state_dict(state_dict, strict, assign)
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

    def obs_to_tensor(self, observation: np.ndarray | dict[str, np.ndarray]) -> tuple[PyTorchObs, bool]:
        """SB3's conversion, after checking what a user hands to ``predict``
        (:func:`~sb3_taskalloc.common.spaces.check_observation`)."""
        check_observation(observation, self.observation_space)  # type: ignore[arg-type]
        return super().obs_to_tensor(observation)

    def parse(self, obs: PyTorchObs) -> ObsView:
        """The typed, normalised view of a batch of observations."""
        if not isinstance(obs, dict):
            raise TypeError(f"TAMPolicy needs the Dict observations of a TaskAlloc env, got {type(obs).__name__}")
        return parse_obs(obs)

    def select_view(self, view: ObsView) -> ObsView:
        """The view the pointer decodes and trains on: ``view`` with :attr:`select_values` in its pair costs, if any."""
        return view if self.select_values is None else self.select_values.costed(view)

    def select_round(self, view: ObsView, task_of: th.Tensor, deterministic: bool, uniform: bool = False) -> SelectState:
        """Decode the teams of every task of one round in parallel on :meth:`select_view` (:func:`.decode_round`)."""
        return decode_round(self.selector.head, self.select_view(view), task_of, deterministic, uniform)

    def decide(
        self,
        view: ObsView,
        deterministic: bool = False,
        uniform: bool = False,
        rounds_out: list[tuple[ObsView, th.Tensor]] | None = None,
    ) -> Decision:
        """Both stages on a batch of observations (paper Algorithm 1).

        :param view: parsed observations
        :param deterministic: decode by :attr:`decoder` (the argmax unless set otherwise); else sample, as training does
        :param uniform: uniform random choices at both stages (warm-up exploration)
        :param rounds_out: when given, every pre-assign round appends its view and candidate sets ``task_of`` (B, N)
            to it: the states the select stage decoded, which the first-round decision alone does not record
        """
        if self.preassign:
            graph = self.decision_graph if rounds_out is None else None
            recorded = None if graph is None else graph.decide(self, view, deterministic, uniform)
            if recorded is not None:
                return recorded
            decoder = UNIFORM if uniform else self.decoder if deterministic else SAMPLED
            return decoder.decide(self, view, rounds_out)
        if rounds_out is not None:
            raise ValueError("rounds_out needs a pre-assigning policy: without pre-assignment the tasks share one pool")
        # Without pre-assignment the tasks share one pool, so the decoders' searches do not apply: argmax or samples.
        return decide_pooled(self, view, deterministic and self.decoder.deterministic, uniform)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        with th.inference_mode():  # cheaper than SB3's no_grad for the sequential decoding
            return self.decide(self.parse(observation), deterministic).env_action

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(obs, deterministic)


def _frozen_copy(module: nn.Module) -> Any:
    """A constant copy of ``module`` (no gradients, eval mode, no optimizer)."""
    prior = copy.deepcopy(module).requires_grad_(False).train(False)
    if hasattr(prior, "optimizer"):
        del prior.optimizer
    return prior


def _scale_last_layer(net: nn.Sequential, gain: float) -> None:
    last = net[-1]
    assert isinstance(last, nn.Linear)
    last.weight.mul_(gain)
    last.bias.mul_(gain)


#: TAMPolicy's defaults of the keywords that decide whether its pre-assign actor starts at a rule (:func:`starts_at_rule`).
_RULE_DEFAULTS: dict[str, Any] = {
    name: parameter.default
    for name, parameter in inspect.signature(TAMPolicy.__init__).parameters.items()
    if name in ("heuristic_init", "preassign", "encoder", "pair_features")
}
