"""Helpers of the experiment runners' tests: shorter EPT episodes in the runners' worker processes, and a record of
the DAgger calls a runner makes (the fixtures that use them: ``conftest.py``)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import pytest


def record_distill_select(monkeypatch: pytest.MonkeyPatch) -> list[tuple[Any, dict[str, Any]]]:
    """Each call of ``TwoStageSAC.distill_select`` from here on, as (the rollouts' env, its keywords but the
    per-iteration callback)."""
    from sb3_taskalloc import TwoStageSAC

    calls: list[tuple[Any, dict[str, Any]]] = []
    real = TwoStageSAC.distill_select

    def recorded(self: TwoStageSAC, env: Any, callback: Any = None, **kw: Any) -> Any:
        calls.append((env, kw))
        return real(self, env, callback=callback, **kw)

    monkeypatch.setattr(TwoStageSAC, "distill_select", recorded)
    return calls


#: EPT's episode length in the runners' plumbing tests (registered: 100)
SHORT_EPT_STEPS = 12


def short_worker(parent: int) -> None:
    """The learning experiment's worker set-up (``jobs > 1``) with :data:`SHORT_EPT_STEPS`-step EPT episodes."""
    from sb3_taskalloc.experiments.evaluation import one_thread

    one_thread(parent)
    gym.spec("TaskAlloc/EPT-v0").max_episode_steps = SHORT_EPT_STEPS
