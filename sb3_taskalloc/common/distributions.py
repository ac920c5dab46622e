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

    def get_actions(self, deterministic: bool) -> th.Tensor:
        """(...) the most probable index, or one drawn by the Gumbel-max trick (see :func:`masked_pick`)."""
        return masked_pick(self.logits, deterministic)


def masked_pick(masked_logits: th.Tensor, deterministic: bool) -> th.Tensor:
    """Index along the last axis: argmax of logits already filled with ``NEG`` where masked, or a sample of their
    softmax by the Gumbel-max trick (torch's global RNG, so ``set_random_seed`` applies). No softmax is computed."""
    if not deterministic:
        u = th.rand_like(masked_logits).clamp_(1e-10, 1.0 - 1e-7)
        masked_logits = masked_logits - th.log(-th.log(u))
    return th.argmax(masked_logits, dim=-1)
