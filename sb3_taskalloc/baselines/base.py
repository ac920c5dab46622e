"""Common interface of the baselines: SB3's ``predict`` on TaskAlloc observations (single or vectorised)."""

from __future__ import annotations

import numpy as np


class Allocator:
    """Base class: subclasses implement :meth:`allocate` for one observation; :meth:`predict` follows SB3's signature
    so ``evaluate_policy`` and the experiment runner treat baselines like models."""

    def allocate(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """(N,) env action for one (unbatched) observation."""
        raise NotImplementedError

    def predict(
        self,
        observation: dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """:param observation: a TaskAlloc observation dict, single or batched (leading env axis)
        :return: the action(s) and ``None`` (no recurrent state)"""
        if not isinstance(observation, dict) or "entity_mask" not in observation:
            raise ValueError("baselines need the Dict observations of a TaskAlloc env (keys entity_mask, task_mask, ...)")
        if np.ndim(observation["entity_mask"]) == 2:
            n = len(observation["entity_mask"])
            return np.stack([self.allocate({k: np.asarray(v)[b] for k, v in observation.items()}) for b in range(n)]), None
        return self.allocate({k: np.asarray(v) for k, v in observation.items()}), None

    def reset(self, seed: int | None = None) -> None:
        """Reset internal state (planners); stateless allocators ignore it."""
