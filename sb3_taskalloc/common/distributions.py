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

    def sample(self) -> th.Tensor:
        """(...) index drawn by the Gumbel-max trick (uses torch's global RNG, so ``set_random_seed`` applies)."""
        u = th.rand_like(self.logits).clamp_(1e-10, 1.0 - 1e-7)
        return th.argmax(self.logits - th.log(-th.log(u)), dim=-1)

    def mode(self) -> th.Tensor:
        """(...) most probable index."""
        return th.argmax(self.logits, dim=-1)

    def get_actions(self, deterministic: bool) -> th.Tensor:
        return self.mode() if deterministic else self.sample()

    def log_prob(self, index: th.Tensor) -> th.Tensor:
        """(...) log-probability of ``index`` (0 for empty rows)."""
        return th.gather(self.log_probs, -1, index.clamp_min(0).unsqueeze(-1)).squeeze(-1)

    def expectation(self, values: th.Tensor) -> th.Tensor:
        """(...) Σ_c p_c · values_c."""
        return (self.probs * values).sum(-1)
