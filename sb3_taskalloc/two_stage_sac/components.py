"""The components of :class:`~sb3_taskalloc.TAMPolicy` chosen by name: its encoder (the scorer of the pre-assign actor
and of each per-entity critic) and its stage-1 critic's mixer. The ablations of the paper's table are the names other
than the defaults: ``encoder="mlp"`` (W/o TAM) and ``mixer="global"`` (W/o AMIX). A component is built from the
policy (its sizes and settings) and declares whether it is ``size_agnostic``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from torch import nn

from sb3_taskalloc.common.mixers import AMIXMixer, GlobalMixer, TeamValue
from sb3_taskalloc.common.policies import AMIXCritic, GlobalCritic
from sb3_taskalloc.common.torch_layers import FlatScorer, PairScorer


def _tam_scorer(policy: Any, scale: float) -> nn.Module:
    _, _, Fe, Ft, _ = policy.dims
    return PairScorer(Fe, Ft, policy.hidden_dim, scale, policy.pair_features, policy.n_attention_layers, policy.activation_fn)


def _flat_scorer(policy: Any, scale: float) -> nn.Module:
    N, M, Fe, Ft, _ = policy.dims
    return FlatScorer(N, M, Fe, Ft, policy.hidden_dim, policy.activation_fn)


def _amix_critic(policy: Any) -> AMIXCritic:
    _, _, Fe, Ft, K = policy.dims
    settings = policy.mixer_kwargs
    mixer = AMIXMixer(Fe, Ft, policy.hidden_dim, settings["monotonic"], settings["hyper_bias"], policy.activation_fn)
    team = TeamValue(Ft, K, policy.hidden_dim, policy.activation_fn) if settings["team_value"] else None
    return AMIXCritic(policy._scorer(scale=1.0), mixer, team)  # critics unscaled: Q-values need no temperature


def _global_critic(policy: Any) -> GlobalCritic:
    N, M, Fe, Ft, _ = policy.dims
    return GlobalCritic(GlobalMixer(N, M, Fe, Ft, policy.hidden_dim, policy.activation_fn))


#: ``encoder`` name -> the scorer of the actor and of each per-entity critic (built with the actor's or critic's scale).
ENCODERS: dict[str, Callable[[Any, float], nn.Module]] = {"tam": _tam_scorer, "mlp": _flat_scorer}
#: ``mixer`` name -> one stage-1 critic.
MIXERS: dict[str, Callable[[Any], AMIXCritic | GlobalCritic]] = {"amix": _amix_critic, "global": _global_critic}
