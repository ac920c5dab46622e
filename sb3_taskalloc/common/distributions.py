"""Masked categorical distributions used by both stages (no NaN for all-masked rows)."""

from __future__ import annotations

import torch as th

from sb3_taskalloc.common.torch_layers import NEG


class MaskedCategorical:
    """Categorical distributions over the last axis restricted to ``mask``.

    Rows whose mask is empty get zero probabilities, zero entropy and an arbitrary (ignored) sample.

    :param logits: (..., C) unnormalised scores
    :param mask: (..., C) bool, True where a choice is allowed
    """

    def __init__(self, logits: th.Tensor, mask: th.Tensor) -> None:
        self.mask = mask
        self.row_valid = mask.any(-1)
        self.logits = logits.masked_fill(~mask, NEG)
        log_probs = th.log_softmax(self.logits, dim=-1)
        self.probs = log_probs.exp() * mask * self.row_valid.unsqueeze(-1)
        self.log_probs = log_probs.masked_fill(~mask, 0.0)

    def entropy(self) -> th.Tensor:
        """(...) entropy −Σ_c p_c log p_c (0 for empty rows)."""
        return -(self.probs * self.log_probs).sum(-1)

    def kl(self, other: MaskedCategorical) -> th.Tensor:
        """(...) KL(self ‖ other) = Σ_c p_c (log p_c − log q_c) over the allowed choices (0 for empty rows)."""
        return (self.probs * (self.log_probs - other.log_probs)).sum(-1)

    def get_actions(self, deterministic: bool) -> th.Tensor:
        """(...) the most probable index, or one drawn by the Gumbel-max trick (see :func:`masked_pick`)."""
        return masked_pick(self.logits, deterministic)


def masked_pick(masked_logits: th.Tensor, deterministic: bool, generator: th.Generator | None = None) -> th.Tensor:
    """Index along the last axis: argmax of logits already filled with ``NEG`` where masked, or a sample of their
    softmax by the Gumbel-max trick (``generator``, by default torch's global RNG, so ``set_random_seed`` applies).
    No softmax is computed."""
    if not deterministic:
        u = th.rand(masked_logits.shape, generator=generator, dtype=masked_logits.dtype, device=masked_logits.device)
        u = u.clamp_(1e-10, 1.0 - 1e-7)
        masked_logits = masked_logits - th.log(-th.log(u))
    return th.argmax(masked_logits, dim=-1)


def segment_pick(
    scores: th.Tensor,
    allowed: th.Tensor,
    seg: th.Tensor,
    n_seg: int,
    deterministic: bool,
    generator: th.Generator | None = None,
    uniforms: th.Tensor | None = None,
) -> th.Tensor:
    """:func:`masked_pick` of every segment at once, computed on (B, N) instead of (B, M, N): the same picks as
    ``masked_pick(scores.unsqueeze(1).masked_fill(~mask, NEG), ...)`` where ``mask[b, j, i]`` is ``allowed[b, i]`` and
    ``seg[b, i] == j``, for every segment with an allowed entity (a segment without one gets entity 0), and the
    sample follows the same distribution: the softmax of each segment's allowed scores.

    :param scores: (B, N) unmasked scores
    :param allowed: (B, N) bool, entities that may be picked
    :param seg: (B, N) segment of each entity in [0, n_seg) (masked entities may point anywhere)
    :param n_seg: number of segments M
    :param deterministic: the first maximum of each segment (else a Gumbel-max sample)
    :param generator: the random stream of the sample (None: torch's global one)
    :param uniforms: (B, N) the sample's uniforms, drawn by the caller (None: drawn here from ``generator``)
    :return: (B, M) the entity picked in each segment
    """
    B, N = scores.shape
    if not deterministic:
        # One uniform per entity: each entity takes part in one segment's draw, so the Gumbel-max of every segment
        # reads independent noise, as with a (B, M, N) draw, at 1/M of its cost.
        if uniforms is None:
            uniforms = th.rand((B, N), generator=generator, dtype=scores.dtype, device=scores.device)
        u = uniforms.clamp(1e-10, 1.0 - 1e-7)
        scores = scores - th.log(-th.log(u))
    scores = scores.masked_fill(~allowed, -th.inf)
    best = scores.new_full((B, n_seg), -th.inf).scatter_reduce_(1, seg, scores, "amax")
    # argmax's tie rule: the first index that reaches its segment's maximum.
    at_best = allowed & (scores == th.gather(best, 1, seg))
    index = th.arange(N, device=scores.device).expand(B, N)
    first = th.full((B, n_seg), N, dtype=th.long, device=scores.device)
    first.scatter_reduce_(1, seg, th.where(at_best, index, N), "amin")
    return first.masked_fill_(first == N, 0)


def segment_sum(x: th.Tensor, seg: th.Tensor, n_seg: int, vector: bool = False) -> th.Tensor:
    """Sum entity values into their segments (the task each entity is a candidate of).

    :param x: (..., B, N) values per entity, or (..., B, N, K) with ``vector=True``
    :param seg: (B, N) segment of each entity in [0, n_seg) (or already expanded to x's entity shape)
    :param n_seg: number of segments M
    :param vector: x has a trailing feature axis
    :return: (..., B, M), or (..., B, M, K) with ``vector=True``
    """
    if vector:
        out = x.new_zeros(*x.shape[:-2], n_seg, x.shape[-1])
        return out.scatter_add_(-2, seg.unsqueeze(-1).expand_as(x), x)
    return x.new_zeros(*x.shape[:-1], n_seg).scatter_add_(-1, seg.expand_as(x), x)


class SegmentedCategorical:
    """One categorical per segment over the entities of that segment, kept in (..., B, N) tensors: entity i belongs to
    segment ``seg[b, i]`` (the task it is a candidate of). Equal to :class:`MaskedCategorical` over (..., B, M, N)
    logits that repeat each entity's logit in its own task's row and mask the others, at 1/M of the size. Segments
    without an allowed entity get zero probabilities and entropy.

    :param logits: (..., B, N) scores
    :param mask: (..., B, N) bool, allowed choices
    :param seg: (B, N) segment of each entity in [0, n_seg) (masked entities may point anywhere)
    :param n_seg: number of segments M
    """

    def __init__(self, logits: th.Tensor, mask: th.Tensor, seg: th.Tensor, n_seg: int) -> None:
        self.mask, self.n_seg = mask, n_seg
        self.seg = seg.expand_as(mask)
        masked = logits.masked_fill(~mask, NEG)
        with th.no_grad():  # a per-segment shift for stability; the log-softmax does not depend on it
            shift = masked.new_full((*mask.shape[:-1], n_seg), NEG).scatter_reduce_(-1, self.seg, masked, "amax")
        z = masked - th.gather(shift, -1, self.seg)
        den = segment_sum(th.exp(z) * mask, self.seg, n_seg)
        log_probs = z - th.log(th.gather(den, -1, self.seg).clamp_min(1e-30))
        self.log_probs = log_probs.masked_fill(~mask, 0.0)
        self.probs = th.exp(self.log_probs) * mask

    def expect(self, values: th.Tensor) -> th.Tensor:
        """(..., B, M) Σ_i π(i) values_i over each segment's entities."""
        return segment_sum(self.probs * values, self.seg, self.n_seg)

    def entropy(self) -> th.Tensor:
        """(..., B, M) entropy of each segment's distribution."""
        return -self.expect(self.log_probs)

    def kl(self, other: SegmentedCategorical) -> th.Tensor:
        """(..., B, M) KL(self ‖ other) of each segment's distribution (same mask and segments)."""
        return self.expect(self.log_probs - other.log_probs)
