"""Mixers of the stage-1 critics: AMIX (the paper's attention-hypernetwork mixer), its linear form for the future
critic, the per-task team value added to it, and the global MLP of "W/o AMIX"."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch as th
from torch import nn

from sb3_taskalloc.common.torch_layers import NEG, FlatNet, ObsView, linear, mlp, symlog


class MixContext(NamedTuple):
    """Action-independent tensors of :class:`AMIXMixer` for a batch of states (reused by the actor loss)."""

    mask: th.Tensor  # (B, N) entities that are mixed (free, with an open task)
    att: th.Tensor  # (B, N, N) SHN attention
    v: th.Tensor  # (B, N, H) SHN values
    weights: th.Tensor | None  # (B, N, H) |A V| when monotonic
    bias: th.Tensor  # (B, H) hyper-bias

    def detach(self) -> MixContext:
        weights = None if self.weights is None else self.weights.detach()
        return MixContext(self.mask, self.att.detach(), self.v.detach(), weights, self.bias.detach())


class AMIXMixer(nn.Module):
    """Attention-hypernetwork mixer (AMIX with its self-attention hypernetwork SHN).

    SHN: X = entity features ⊙ free mask; K = k(X), Q = q(X) (linear, ``attention_dim``), V = v(X) (linear; the
    published code used 2-layer MLPs, linear maps keep the mixer cheap for hundreds of entities);
    A = softmax(K Qᵀ / √d) over free entities; one weight vector per entity w_i = (A V)_i. Hyper-bias
    b = MLP(mean of present entities' features, mean of open tasks' features) gives the state value when no entity is
    free. hidden = ReLU(Σ_i Q_i w_i + b),
    Q_tot = MLP(hidden). Masked entities contribute nothing. ``monotonic``: |w_i| and a non-negative output layer
    (QMIX-style monotonic mixing).

    :param entity_dim: entity feature size
    :param task_dim: task feature size
    :param hidden_dim: hypernetwork width
    :param monotonic: constrain ∂Q_tot/∂Q_i ≥ 0
    :param hyper_bias: state-dependent bias (else a learned constant)
    :param activation_fn: activation
    """

    size_agnostic = True

    def __init__(
        self,
        entity_dim: int,
        task_dim: int,
        hidden_dim: int = 64,
        monotonic: bool = False,
        hyper_bias: bool = True,
        activation_fn: type[nn.Module] = nn.ReLU,
        attention_dim: int = 16,
    ) -> None:
        super().__init__()
        self.k = linear(entity_dim, attention_dim)
        self.q = linear(entity_dim, attention_dim)
        self.v = linear(entity_dim, hidden_dim)
        self.attention_dim = attention_dim
        self.monotonic = monotonic
        self.bias: nn.Module | None = mlp(entity_dim + task_dim, hidden_dim, hidden_dim, activation_fn) if hyper_bias else None
        self.const_bias = nn.Parameter(th.zeros(hidden_dim))
        if monotonic:
            self.out_w = nn.Parameter(th.rand(hidden_dim) / hidden_dim)
            self.out_b = nn.Parameter(th.zeros(1))
        else:
            self.out = mlp(hidden_dim, hidden_dim, 1, activation_fn)

    def context(self, view: ObsView) -> MixContext:
        """The action-independent part of the mixer for a batch of states: attention, values and hyper-bias."""
        mask = view.assignable
        x = view.entity * mask.unsqueeze(-1)
        k, q, v = self.k(x), self.q(x), self.v(x)
        # K Qᵀ/√d plus the additive key mask in one batched GEMM (no separate (B, N, N) pass for the scale or the mask).
        key_bias = ((~mask).float() * NEG).unsqueeze(1)  # (B, 1, N)
        att = th.softmax(th.baddbmm(key_bias, k, q.transpose(1, 2), alpha=1 / math.sqrt(self.attention_dim)), dim=-1)
        bias = self.const_bias.expand(mask.shape[0], -1)
        if self.bias is not None:
            pres = view.present.unsqueeze(-1).float()
            tmask = view.task_mask.unsqueeze(-1).float()
            ent_mean = (view.entity * pres).sum(1) / pres.sum(1).clamp_min(1)
            task_mean = (view.task * tmask).sum(1) / tmask.sum(1).clamp_min(1)
            bias = bias + self.bias(th.cat([ent_mean, task_mean], -1))
        if self.monotonic:
            return MixContext(mask, att, v, (att @ v).abs(), bias)  # one hyper-weight vector per entity
        return MixContext(mask, att, v, None, bias)

    def mix(self, q_i: th.Tensor, ctx: MixContext) -> th.Tensor:
        """:param q_i: (B, N) per-entity values; :param ctx: :meth:`context` of the states; :return: (B,) Q_tot"""
        q_i = (q_i * ctx.mask).unsqueeze(1)  # (B, 1, N)
        # Σ_i Q_i (A V)_i, computed as (Qᵀ A) V without monotonicity: O(N²) instead of O(N²H).
        mixed = (q_i @ ctx.weights if ctx.weights is not None else (q_i @ ctx.att) @ ctx.v).squeeze(1)
        hidden = th.relu(mixed + ctx.bias)
        if self.monotonic:
            return hidden @ self.out_w.abs() + self.out_b
        return self.out(hidden).squeeze(-1)

    def forward(self, q_i: th.Tensor, view: ObsView) -> th.Tensor:
        """:param q_i: (B, N) per-entity values; :return: (B,) Q_tot"""
        return self.mix(q_i, self.context(view))


class TeamValue(nn.Module):
    """Value of the teams an assignment sends, task by task (not in the paper): V(s, a) = Σ_{j open} g(z_j) with
    z_j = [task features, supply share per resource min(Σ_i a_ij x_ik / d_jk, 2), its minimum over resources,
    symlog Σ_i a_ij c_ij, symlog Σ_i a_ij].

    AMIX mixes per-entity values Q_i(s, c_i), none of which depends on who else is a candidate of the same task, so it
    cannot tell a candidate set that covers its task from one that does not. g sees each task's aggregate supply, cost and
    size. With policy probabilities a = π the aggregates are their expectations (mean field), which the actor loss
    differentiates: the gradient moves entities towards tasks whose expected supply falls short of their demand.

    :param task_dim: task feature size
    :param n_resources: K
    :param hidden_dim: width of g
    :param activation_fn: activation
    """

    size_agnostic = True

    def __init__(
        self, task_dim: int, n_resources: int, hidden_dim: int = 64, activation_fn: type[nn.Module] = nn.ReLU
    ) -> None:
        super().__init__()
        self.g = mlp(task_dim + n_resources + 3, hidden_dim, 1, activation_fn)

    def forward(self, view: ObsView, assign: th.Tensor) -> th.Tensor:
        """:param assign: (B, N, M) one-hot assignment or assignment probabilities; :return: (B,)"""
        supply = th.einsum("bnm,bnk->bmk", assign, view.supply)
        need = view.demand > 0
        share = th.where(need, supply / view.demand.clamp_min(1e-6), 2.0).clamp_max(2.0)
        cost = (assign * view.pair_cost).sum(1)
        z = th.cat([view.task, share, share.min(-1, keepdim=True).values, symlog(cost).unsqueeze(-1),
                    symlog(assign.sum(1)).unsqueeze(-1)], -1)  # fmt: skip
        return (self.g(z).squeeze(-1) * view.task_mask).sum(-1)


class GlobalMixer(FlatNet):
    """The "W/o AMIX" ablation: one MLP over flattened tasks, entities and the (one-hot or expected) assignment → Q_tot."""

    name = 'mixer="global"'

    @staticmethod
    def outputs(n_entities: int, n_tasks: int) -> int:
        return 1

    def forward(self, assign: th.Tensor, view: ObsView) -> th.Tensor:
        """:param assign: (B, N, M) one-hot pre-assignment or assignment probabilities; :return: (B,)"""
        return self.flat_forward(view, assign).squeeze(-1)
