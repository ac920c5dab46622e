"""Callbacks of TwoStageSAC's training schedule, for ``learn(callback=...)`` and rl-zoo3's ``callback`` key."""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any, ClassVar

import gymnasium as gym
from gymnasium.envs.registration import EnvSpec
from stable_baselines3.common.callbacks import BaseCallback

from sb3_taskalloc.common.utils import check_bools
from sb3_taskalloc.two_stage_sac.dagger import check_distill_select, teacher_costs
from sb3_taskalloc.two_stage_sac.two_stage_sac import TwoStageSAC


def dagger_seed(seed: int) -> int:
    """Seed of the DAgger rollouts' env for a model trained under ``seed``: ``50_000 + 1000·seed``. The env's first reset
    takes it (a VecEnv's copies take it, it + 1, ...) and later episodes follow the env's own stream, so the rollouts
    of different training seeds start from different seeds (for up to 1,000 copies), none of them a seed the training
    envs of the same seed start from.

    :param seed: the model's seed
    :return: the seed of the rollouts' env
    """
    return 50_000 + 1000 * seed


class SelectDAggerCallback(BaseCallback):
    """Runs :meth:`~sb3_taskalloc.TwoStageSAC.distill_select` when ``learn`` ends: after the TwoStageSAC steps, the pointer
    is taught the exact most profitable cover of its candidates by DAgger (implementation detail 19). This puts the
    DAgger phase into one ``learn`` call or an rl-zoo3 config::

        callback:
          - sb3_taskalloc.two_stage_sac.callbacks.SelectDAggerCallback:
              iterations: 8
              imitation: set

    The rollouts run on a fresh env made from the training env's spec (its id, keywords and time limit, without its
    wrappers; one copy, so they do not disturb the training envs), and the next ``learn`` call of the model resets its
    training envs before it collects again. With ``learn(progress_bar=True)`` SB3's bar closes when the steps end and
    DAgger shows its own.

    :param iterations: rollout-label-fit iterations
    :param episodes: episodes rolled out per iteration
    :param epochs: passes over the labels per iteration
    :param learning_rate: Adam's step size of the fit
    :param batch_size: decoding rounds per gradient step of the fit
    :param imitation: ``"sequence"`` or ``"set"`` (see ``distill_select``)
    :param teacher: the costs of the teacher's covers (see ``distill_select``): None, the pointer's own;
        ``"recommended"``, those of the training env's recommended decoder (checked when ``learn`` starts)
    :param seed: seed of the rollouts' env; None: :func:`dagger_seed` of the model's seed (the episodes of
        ``python -m sb3_taskalloc.experiments learn --select-dagger``), or unseeded when the model has no seed
    :param after_interrupt: whether DAgger still runs when training ended early (Ctrl-C: rl-zoo3 then ends the callbacks
        and saves the model). False, the default: it is skipped with a warning, so the model is saved at once. Ctrl-C
        during DAgger stops it after the iteration in progress; the model keeps the iterations done
    :param verbose: 1 prints each iteration's figures
    """

    #: ``learn`` recognises it by this, to close SB3's progress bar before DAgger and show DAgger's instead.
    distills_select: ClassVar[bool] = True

    def __init__(
        self,
        iterations: int = 4,
        episodes: int = 10,
        epochs: int = 8,
        learning_rate: float = 1e-3,
        batch_size: int = 32,
        imitation: str = "sequence",
        teacher: str | None = None,
        seed: int | None = None,
        after_interrupt: bool = False,
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose)
        check_bools({"after_interrupt": after_interrupt})
        self.after_interrupt = after_interrupt
        # Checked here, before training, not after it.
        check_distill_select(iterations, episodes, epochs, learning_rate, batch_size, imitation, teacher)
        self.kwargs: dict[str, Any] = {
            "iterations": iterations,
            "episodes": episodes,
            "epochs": epochs,
            "learning_rate": learning_rate,
            "batch_size": batch_size,
            "imitation": imitation,
            "teacher": teacher,
        }
        self.seed = seed
        self.history: list[dict[str, float]] = []
        self.progress_bar = False  # set by each ``learn`` call from its own ``progress_bar``
        self._distilled = False  # whether this learn() call's DAgger has run

    def _init_callback(self) -> None:
        # Checked when learn() starts, so that a model or env it cannot distil fails before the training steps.
        if not isinstance(self.model, TwoStageSAC):
            raise TypeError(f"SelectDAggerCallback needs a TwoStageSAC model, got {type(self.model).__name__}")
        self.model.check_distillable()
        spec = self.training_env.get_attr("spec", indices=0)[0]
        if spec is None:
            raise ValueError("SelectDAggerCallback needs a registered training env: its spec makes the rollouts' env")
        self.env_spec: EnvSpec = spec
        teacher_costs(self.kwargs["teacher"], spec.id)  # an env without a recommended decoder fails here, not after training

    def _on_training_start(self) -> None:
        self._distilled = False

    def _on_step(self) -> bool:
        return True

    def _on_training_end(self) -> None:
        # Once per learn() call: rl-zoo3 calls the first callback's on_training_end again after learn() returns (to
        # close a progress bar), which would run a second DAgger.
        if self._distilled:
            return
        self._distilled = True
        assert isinstance(self.model, TwoStageSAC)
        planned = self.model._total_timesteps
        if self.model.num_timesteps < planned and not self.after_interrupt:
            warnings.warn(
                f"training ended at env step {self.model.num_timesteps} of {planned}: SelectDAggerCallback skips DAgger "
                "(after_interrupt=True runs it anyway)",
                stacklevel=2,
            )
            return
        seed = self.seed if self.seed is not None else None if self.model.seed is None else dagger_seed(self.model.seed)
        # The spec's wrappers (a Monitor, say) are left out: its id, keywords and time limit make the env.
        env = gym.make(dataclasses.replace(self.env_spec, additional_wrappers=()))
        self.history = []
        try:  # each iteration is recorded as it ends, so Ctrl-C keeps the ones done and lets the caller save the model
            self.model.distill_select(
                env, seed=seed, callback=self.history.append, progress_bar=self.progress_bar, **self.kwargs
            )
        except KeyboardInterrupt:
            warnings.warn(
                f"DAgger interrupted after {len(self.history)} of {self.kwargs['iterations']} iterations; the model keeps "
                "them",
                stacklevel=2,
            )
        for stats in self.history:
            for key, value in stats.items():
                self.logger.record(f"dagger/{key}", value)
            self.logger.dump(self.num_timesteps)
        self.model._last_obs = None  # type: ignore[assignment]  # a later learn() resets the training envs
