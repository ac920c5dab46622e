"""Utilities shared by the algorithms."""

from __future__ import annotations

from collections.abc import Iterable

import torch as th


@th.no_grad()
def foreach_polyak_update(params: Iterable[th.Tensor], target_params: Iterable[th.Tensor], tau: float) -> None:
    """SB3's :func:`~stable_baselines3.common.utils.polyak_update` (θ' ← (1 − τ)·θ' + τ·θ, the same arithmetic) with
    one multi-tensor kernel per operation instead of a Python loop over the parameters."""
    params, target_params = list(params), list(target_params)
    if len(params) != len(target_params):
        raise ValueError(f"{len(params)} parameters but {len(target_params)} target parameters")
    th._foreach_mul_(target_params, 1 - tau)
    th._foreach_add_(target_params, params, alpha=tau)
