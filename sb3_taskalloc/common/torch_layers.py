"""Building blocks of the two-stage method: input normalisation, the TAM encoder and scorers, the pointer head.

All modules take padded, masked batches and never produce NaN for all-masked rows. Every module that scores or mixes
declares ``size_agnostic``: whether it accepts any number of entities and tasks (a model transfers to another size only
when all of its modules do).
"""

from __future__ import annotations

import itertools
import math
from typing import Any, NamedTuple

import torch as th
from torch import nn

#: Large negative logit used instead of -inf inside attention (keeps all-masked rows finite).
NEG = -1e9


def symlog(x: th.Tensor) -> th.Tensor:
    """sign(x)·log(1 + |x|): scale-robust input normalisation (no statistics, size-agnostic)."""
    return th.sign(x) * th.log1p(th.abs(x))


def zero_output(net: nn.Sequential) -> bool:
    """Whether the last linear layer of ``net`` is identically zero, so that ``net`` outputs 0 for every input."""
    last = net[-1]
    return isinstance(last, nn.Linear) and not bool(last.weight.any()) and (last.bias is None or not bool(last.bias.any()))


class _NarrowInputLinear(th.autograd.Function):
    """y = x Wᵀ + b whose weight gradient is formed as (xᵀ ∂y)ᵀ rather than ∂yᵀ x (see :class:`NarrowLinear`)."""

    @staticmethod
    def forward(x: th.Tensor, weight: th.Tensor, bias: th.Tensor | None) -> th.Tensor:  # type: ignore[override]
        return nn.functional.linear(x, weight, bias)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[th.Tensor, th.Tensor, th.Tensor | None], output: th.Tensor) -> None:
        x, weight, _ = inputs
        ctx.save_for_backward(x, weight)

    @staticmethod
    @th.autograd.function.once_differentiable
    def backward(ctx: Any, grad: th.Tensor) -> tuple[th.Tensor | None, ...]:  # type: ignore[override]
        x, weight = ctx.saved_tensors
        grad_x = grad @ weight if ctx.needs_input_grad[0] else None
        g2 = grad.reshape(-1, grad.shape[-1])
        grad_w = (x.reshape(-1, x.shape[-1]).t() @ g2).t() if ctx.needs_input_grad[1] else None
        grad_b = g2.sum(0) if ctx.needs_input_grad[2] else None
        return grad_x, grad_w, grad_b


class NarrowLinear(nn.Linear):
    """:class:`torch.nn.Linear` for few input features (the raw entity and task features) applied to many rows.

    The same function and gradients; only the product that forms the weight gradient is reordered. For a (rows × 8)
    input and 64 outputs, MKL forms ∂yᵀx (autograd's order) about 7× slower on a CPU thread than (xᵀ∂y)ᵀ, and a batch
    holds B·N entity rows (6,400 on RBF). Below :attr:`min_rows` rows the plain layer is used: there the custom autograd
    function's Python overhead outweighs the gain.
    """

    #: Fewest input rows for which the reordered weight gradient is used.
    min_rows = 1024

    def forward(self, x: th.Tensor) -> th.Tensor:
        rows = x.numel() // max(self.in_features, 1)
        if rows >= self.min_rows and th.is_grad_enabled() and (x.requires_grad or self.weight.requires_grad):
            return _NarrowInputLinear.apply(x, self.weight, self.bias)
        return nn.functional.linear(x, self.weight, self.bias)


def linear(in_dim: int, out_dim: int) -> nn.Linear:
    """``nn.Linear(in_dim, out_dim)``, as a :class:`NarrowLinear` for a narrow input and a wide output."""
    return NarrowLinear(in_dim, out_dim) if in_dim <= 16 <= out_dim else nn.Linear(in_dim, out_dim)


def mlp(in_dim: int, hidden: int, out_dim: int, activation_fn: type[nn.Module] = nn.ReLU, n_hidden: int = 1) -> nn.Sequential:
    """``in → hidden (→ hidden …) → out`` with ``activation_fn`` between layers (the paper's 2-layer MLPs by default)."""
    layers: list[nn.Module] = [linear(in_dim, hidden), activation_fn()]
    for _ in range(n_hidden - 1):
        layers += [nn.Linear(hidden, hidden), activation_fn()]
    layers.append(nn.Linear(hidden, out_dim))
    return nn.Sequential(*layers)


def last_hidden(net: nn.Sequential, x: th.Tensor) -> th.Tensor:
    """``net`` without its output layer applied to ``x``: the last hidden layer of an :func:`mlp`."""
    for layer in itertools.islice(net, len(net) - 1):
        x = layer(x)
    return x


class ObsView(NamedTuple):
    """Typed view of a batch of ``TaskAlloc`` observations, with normalised features and boolean masks."""

    entity: th.Tensor  # (B, N, Fe) symlog features
    task: th.Tensor  # (B, M, Ft) symlog features
    supply: th.Tensor  # (B, N, K)
    demand: th.Tensor  # (B, M, K)
    reward: th.Tensor  # (B, M)
    pair_cost: th.Tensor  # (B, N, M)
    entity_mask: th.Tensor  # (B, N) bool: free
    task_mask: th.Tensor  # (B, M) bool: open
    present: th.Tensor  # (B, N) bool: entity exists (free or busy)
    pair: th.Tensor  # (B, N, M, PAIR_FEATURES) fixed pair basis (see :func:`pair_basis`)

    @property
    def valid(self) -> th.Tensor:
        """(B, N, M) bool: entity i may be assigned to task j."""
        return self.entity_mask.unsqueeze(-1) & self.task_mask.unsqueeze(1)

    @property
    def assignable(self) -> th.Tensor:
        """(B, N) bool: free entities that have at least one open task."""
        return self.entity_mask & self.task_mask.any(-1, keepdim=True)


def parse_obs(obs: dict[str, th.Tensor]) -> ObsView:
    """Build an :class:`ObsView` from an observation dict of tensors (batch first)."""
    ent = obs["entity_features"].float()
    supply, demand = obs["entity_supply"].float(), obs["task_demand"].float()
    reward, pc = obs["task_reward"].float(), obs["pair_cost"].float()
    return ObsView(
        entity=symlog(ent),
        task=symlog(obs["task_features"].float()),
        supply=supply,
        demand=demand,
        reward=reward,
        pair_cost=pc,
        entity_mask=obs["entity_mask"].bool(),
        task_mask=obs["task_mask"].bool(),
        present=(ent.abs().sum(-1) > 0) | obs["entity_mask"].bool(),
        pair=pair_basis(pc, coverage(supply, demand), reward),
    )


#: Names of the fixed pair features of :func:`pair_basis`, in order.
PAIR_FEATURE_NAMES = ("pair_cost", "coverage", "margin", "margin_positive", "sole_cover")
#: Number of fixed pair features of :func:`pair_basis`.
PAIR_FEATURES = len(PAIR_FEATURE_NAMES)


def pair_basis(pair_cost: th.Tensor, cover: th.Tensor, reward: th.Tensor) -> th.Tensor:
    """(B, N, M, PAIR_FEATURES) fixed nonlinear features of each (entity, task) pair, computed once per observation
    and shared by every scorer, which weighs them linearly: symlog pair cost, coverage share, symlog margin
    m = symlog(reward − pair cost), its positive part relu(m), and whether the entity alone covers the task.
    A fixed basis with a learned linear read-out instead of a small MLP per scorer: an MLP's hidden layer over every
    pair of every batch row would dominate the cost of a training step."""
    margin = symlog(reward.unsqueeze(1) - pair_cost)
    return th.stack([symlog(pair_cost), cover, margin, th.relu(margin), (cover >= 1 - 1e-6).float()], dim=-1)


def coverage(supply: th.Tensor, demand: th.Tensor) -> th.Tensor:
    """(B, N, M) share of task j's remaining demand that entity i alone covers: Σ_k min(s_ik, d_jk) / Σ_k d_jk."""
    covered = th.minimum(supply.unsqueeze(2), demand.unsqueeze(1)).sum(-1)
    return covered / demand.sum(-1).unsqueeze(1).clamp_min(1e-6)


class MaskedSelfAttention(nn.Module):
    """One pre-norm residual self-attention block over padded tokens (keys restricted to ``mask``)."""

    def __init__(self, dim: int, n_heads: int = 4) -> None:
        super().__init__()
        self.n_heads = n_heads
        self.norm = nn.LayerNorm(dim)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.out = nn.Linear(dim, dim)
        self.ff = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, 2 * dim), nn.ReLU(), nn.Linear(2 * dim, dim))

    def forward(self, x: th.Tensor, mask: th.Tensor) -> th.Tensor:
        B, L, D = x.shape
        h = self.n_heads
        q, k, v = self.qkv(self.norm(x)).view(B, L, 3, h, D // h).permute(2, 0, 3, 1, 4)
        scores = q @ k.transpose(-1, -2) / math.sqrt(D // h)
        scores = scores.masked_fill(~mask[:, None, None, :], NEG)
        att = th.softmax(scores, dim=-1) @ v
        x = x + self.out(att.transpose(1, 2).reshape(B, L, D))
        return x + self.ff(x)


class TAMEncoder(nn.Module):
    """Two-head attention module encoder: entity embeddings h_i = f_h(e_i), task embeddings g_j = f_g(t_j)
    (paper Eq. for TAM), optionally refined by self-attention blocks over entity and task tokens.

    :param entity_dim: entity feature size Fe
    :param task_dim: task feature size Ft
    :param hidden_dim: embedding size d (paper: 64)
    :param n_attention_layers: self-attention blocks over entity tokens and over task tokens (0: plain MLPs)
    :param activation_fn: activation of the MLPs
    """

    def __init__(
        self,
        entity_dim: int,
        task_dim: int,
        hidden_dim: int = 64,
        n_attention_layers: int = 0,
        activation_fn: type[nn.Module] = nn.ReLU,
    ) -> None:
        super().__init__()
        self.f_h = mlp(entity_dim, hidden_dim, hidden_dim, activation_fn)
        self.f_g = mlp(task_dim, hidden_dim, hidden_dim, activation_fn)
        self.entity_blocks = nn.ModuleList(MaskedSelfAttention(hidden_dim) for _ in range(n_attention_layers))
        self.task_blocks = nn.ModuleList(MaskedSelfAttention(hidden_dim) for _ in range(n_attention_layers))

    def forward(self, view: ObsView) -> tuple[th.Tensor, th.Tensor]:
        h = self.f_h(view.entity)
        for block in self.entity_blocks:
            h = block(h, view.present)
        return h, self.embed_tasks(view)

    def embed_tasks(self, view: ObsView) -> th.Tensor:
        """(B, M, d) task embeddings g_j."""
        g = self.f_g(view.task)
        for block in self.task_blocks:
            g = block(g, view.task_mask)
        return g

    def dot(self, view: ObsView, scale: float = 1.0) -> th.Tensor:
        """(B, N, M) h_i·g_j / ``scale`` for every pair.

        Without entity attention blocks, h_i = W z_i + b with z_i the entity MLP's last hidden layer, so
        h_i·g_j = z_i·(Wᵀg_j) + b·g_j: the last layer is applied to the M task embeddings instead of the N entities
        (the same value, reassociated; N ≫ M in the allocation problems), and the product is formed as (B, M, N),
        the layout that is fastest to multiply and differentiate on CPUs."""
        last = self.f_h[-1]
        if self.entity_blocks or not isinstance(last, nn.Linear) or last.bias is None:
            h, g = self(view)
            return h @ g.transpose(1, 2) / scale
        z = last_hidden(self.f_h, view.entity)  # (B, N, d)
        wb = self.embed_tasks(view) @ (th.cat([last.weight, last.bias.unsqueeze(-1)], -1) / scale)  # [Wᵀg_j, b·g_j] / scale
        return th.baddbmm(wb[..., -1:], wb[..., :-1], z.transpose(1, 2)).transpose(1, 2)  # formed as (B, M, N)


class PairScorer(nn.Module):
    """Pairwise score s_ij = h_i·g_j / scale + w·φ_ij: the TAM dot product (paper: /√d for the actor) plus an
    optional learned linear term of the fixed pair basis φ (pair cost, coverage, margin; :func:`pair_basis`).

    :param entity_dim: entity feature size
    :param task_dim: task feature size
    :param hidden_dim: embedding size d
    :param scale: divisor of the dot product (√d for the actor as in the paper, 1 for the critics)
    :param pair_features: add a learned linear term w·φ_ij of the fixed pair basis φ (:func:`pair_basis`)
    :param n_attention_layers: see :class:`TAMEncoder`
    :param activation_fn: activation of the MLPs
    """

    size_agnostic = True

    def __init__(
        self,
        entity_dim: int,
        task_dim: int,
        hidden_dim: int = 64,
        scale: float = 1.0,
        pair_features: bool = True,
        n_attention_layers: int = 0,
        activation_fn: type[nn.Module] = nn.ReLU,
    ) -> None:
        super().__init__()
        self.encoder = TAMEncoder(entity_dim, task_dim, hidden_dim, n_attention_layers, activation_fn)
        self.scale = scale
        self.pair = nn.Linear(PAIR_FEATURES, 1) if pair_features else None
        #: Skip the dot product (set by :meth:`freeze` when the task embeddings are identically 0).
        self.skip_dot = False

    def freeze(self) -> None:
        """Mark the weights as constant: with an all-zero output layer of the task embeddings (a rule-initialised prior,
        see ``TAMPolicy(heuristic_init=True)``) h·g ≡ 0 and the scores are the pair term alone, computed without the
        encoder. Call again after the weights change."""
        self.skip_dot = not self.encoder.task_blocks and zero_output(self.encoder.f_g)

    def forward(self, view: ObsView) -> th.Tensor:
        if self.skip_dot:
            if self.pair is None:
                return view.pair_cost.new_zeros(view.pair_cost.shape)
            return self.pair(view.pair).squeeze(-1)
        scores = self.encoder.dot(view, self.scale)
        if self.pair is not None:
            scores = scores + self.pair(view.pair).squeeze(-1)
        return scores


class FlatNet(nn.Module):
    """MLP over flattened padded entities, tasks and one (N, M) pair tensor: the size-specific ablations. Subclasses set
    :meth:`outputs`, the width of the MLP's output for N entities and M tasks.

    :param n_entities: padded entity count N
    :param n_tasks: padded task count M
    :param entity_dim: entity feature size
    :param task_dim: task feature size
    :param hidden_dim: hidden width
    :param activation_fn: activation
    """

    size_agnostic = False
    name = ""

    @staticmethod
    def outputs(n_entities: int, n_tasks: int) -> int:
        raise NotImplementedError

    def __init__(
        self,
        n_entities: int,
        n_tasks: int,
        entity_dim: int,
        task_dim: int,
        hidden_dim: int = 64,
        activation_fn: type[nn.Module] = nn.ReLU,
    ) -> None:
        super().__init__()
        self.n_entities, self.n_tasks = n_entities, n_tasks
        in_dim = n_entities * entity_dim + n_tasks * task_dim + n_entities * n_tasks
        self.net = mlp(in_dim, hidden_dim, self.outputs(n_entities, n_tasks), activation_fn)

    def flat_forward(self, view: ObsView, pair: th.Tensor) -> th.Tensor:
        N, M = pair.shape[1:]
        if (self.n_entities, self.n_tasks) != (N, M):
            raise ValueError(
                f"{self.name} is size-specific: built for {self.n_entities} entities × {self.n_tasks} tasks, got {N} × {M}; "
                'use the size-agnostic TAM encoder and AMIX mixer (encoder="tam", mixer="amix") to transfer across sizes'
            )
        return self.net(th.cat([view.entity.flatten(1), view.task.flatten(1), pair.flatten(1)], dim=1))


class FlatScorer(FlatNet):
    """The "W/o TAM" ablation: one MLP over the flattened padded inputs (and symlog pair costs) → N·M scores."""

    name = 'encoder="mlp"'

    @staticmethod
    def outputs(n_entities: int, n_tasks: int) -> int:
        return n_entities * n_tasks

    def forward(self, view: ObsView) -> th.Tensor:
        return self.flat_forward(view, symlog(view.pair_cost)).view(-1, self.n_entities, self.n_tasks)


#: Size of the per-step task state of the select stage (remaining demand K + 4 scalars).
SELECT_TASK_EXTRA = 4
#: Size of the per-step dynamic entity features of the select stage that every pointer reads.
SELECT_DYN = 7
#: Index of the symlog unit cost (pair cost per unit of remaining demand covered) in the select stage's dynamic features.
UNIT_COST = 6


class PointerHead(nn.Module):
    """Pointer scores of the select stage for the candidates of each task.

    u_i = d_i·e_j^t / √d + w·x_i^t (+ b(e_j^t) for a critic), where e_j^t encodes task j's state s_j^t after t picks
    (remaining demand, reward, cost so far, number of picks), d_i the entity and x_i^t a fixed basis of its dynamic
    pair features with task j (coverage of the remaining demand, pair cost, margin, waste, unit cost), weighed
    linearly. This dot-product pointer replaces the paper's additive vᵀ tanh(W1 e + W2 d): it needs no
    (batch × entities × hidden) tensor per decoding step, which makes training an order of magnitude cheaper on CPUs.

    :param entity_dim: entity feature size
    :param n_resources: K
    :param hidden_dim: width d
    :param activation_fn: MLP activation
    :param state_value: add a per-task baseline b(e_j^t) (used by the select critics)
    :param logit_scale: κ_s, the scores are multiplied by it (the inverse temperature of the pointer actor)
    """

    def __init__(
        self,
        entity_dim: int,
        n_resources: int,
        hidden_dim: int = 64,
        activation_fn: type[nn.Module] = nn.ReLU,
        state_value: bool = False,
        logit_scale: float = 1.0,
    ) -> None:
        super().__init__()
        self.logit_scale = logit_scale
        task_dim = n_resources + SELECT_TASK_EXTRA
        self.entity = mlp(entity_dim, hidden_dim, hidden_dim, activation_fn)
        self.task = mlp(task_dim, hidden_dim, hidden_dim, activation_fn)
        self.dyn = nn.Linear(SELECT_DYN, 1)  # linear read-out of a fixed nonlinear basis (as the TAM pair term)
        self.value = nn.Linear(hidden_dim, 1) if state_value else None
        self.scale = math.sqrt(hidden_dim)
        #: Skip the dot product (set by :meth:`freeze` when the task embeddings are identically 0).
        self.skip_dot = False

    def freeze(self) -> None:
        """Mark the weights as constant: with an all-zero output layer of the task embeddings (a rule-initialised prior)
        and no baseline, d_i·e_j ≡ 0 and the scores are the linear read-out of the dynamic features alone, computed
        without the entity and task MLPs. Call again after the weights change."""
        self.skip_dot = self.value is None and zero_output(self.task)

    def embed_entities(self, view: ObsView) -> th.Tensor:
        """(B, N, H) entity embeddings d_i (an empty (B, N, 0) tensor when :attr:`skip_dot` makes them unused)."""
        if self.skip_dot:
            return view.entity.new_zeros(*view.entity.shape[:-1], 0)
        return self.entity(view.entity)

    def forward(self, d: th.Tensor, task_state: th.Tensor, dyn: th.Tensor, task_of: th.Tensor) -> th.Tensor:
        """:param d: (B, N, H) entity embeddings, or (B / S, N, H) those of S consecutive copies of each row (a search's
            copies of one state share them); :param task_state: (..., B, M, S) task states (optional leading time
        dims); :param dyn: (..., B, N, SELECT_DYN) the select stage's dynamic features;
        :param task_of: (B, N) task whose candidate entity i is (−1: none)
        :return: (..., B, N) scores (arbitrary for entities with no task; the caller masks them)"""
        linear = self.dyn(dyn).squeeze(-1)
        if self.skip_dot:
            return self._scaled(linear)
        e = self.task(task_state)
        lead = e.shape[:-3]
        B, M, H = e.shape[-3:]
        (B0, N, _), S = d.shape, B // d.shape[0]
        # d_i·e_j for every pair in one batched matmul over the rows of d (no broadcast copies; the copies of a row
        # and the time steps widen its product), then each entity's own column.
        flat = e.reshape(-1, B0, S, M, H).permute(1, 4, 0, 2, 3).reshape(B0, H, -1)  # (B0, H, T·S·M)
        pairs = (d @ flat).view(B0, N, -1, S, M).permute(2, 0, 3, 1, 4).reshape(*lead, B, N, M)
        idx = task_of.clamp_min(0).unsqueeze(-1).expand(*lead, -1, -1, 1)
        scores = th.gather(pairs, -1, idx).squeeze(-1) / self.scale + linear
        if self.value is not None:
            values = self.value(e).squeeze(-1)  # (..., B, M)
            scores = scores + th.gather(values, -1, task_of.clamp_min(0).expand(*lead, -1, -1))
        return self._scaled(scores)

    def _scaled(self, scores: th.Tensor) -> th.Tensor:
        return scores if self.logit_scale == 1.0 else scores * self.logit_scale
