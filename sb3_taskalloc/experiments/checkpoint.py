"""Checkpoints of TwoStageSAC's training in the experiments: the learning experiment's seeds, the table's models.

A checkpoint holds everything that decides how training goes on: the model with its last observations, its replay
buffer, the envs mid-episode (their Monitor logs with them), the random generators and the curve. It is taken at the
start of a collection, after the previous gradient step, so a model resumed from it trains on exactly as it would
have: its figures repeat to the digit.
"""

from __future__ import annotations

import json
import pickle
import random
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.monitor import Monitor, ResultsWriter

from sb3_taskalloc.common.utils import atomic_path, atomic_write_text
from sb3_taskalloc.experiments.evaluation import Curve

#: Wall-clock seconds between a seed's checkpoints: a kill loses at most this much of its training. A checkpoint
#: writes the replay buffer's stored rows (23 KB a transition on RBF: 0.5 GB and under a second at 20,000).
CHECKPOINT_SECONDS = 600.0


class ResumableMonitor(Monitor):
    """SB3's ``Monitor`` that a checkpoint can hold: pickled, it keeps its log file's name and the episodes it logged;
    unpickled, it cuts the file back to them (a kill after the checkpoint logged more) and logs on after them."""

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        writer = state.pop("results_writer")
        state["_log_file"] = None if writer is None else writer.file_handler.name
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        log_file = state.pop("_log_file")
        self.__dict__.update(state)
        self.results_writer = None
        if log_file is not None:
            path = Path(log_file)
            # A JSON line and the header, then a row per episode logged by the checkpoint's time.
            kept = path.read_text().splitlines(keepends=True)[: 2 + len(self.episode_returns)]
            atomic_write_text(path, "".join(kept))
            self.results_writer = ResultsWriter(
                log_file, extra_keys=self.reset_keywords + self.info_keywords, override_existing=False
            )


def training_folder(path: Path) -> Path:
    """The folder of the checkpoints of the training whose model is saved at ``path`` when it ends."""
    return path.with_name(path.stem + "_training")


def keep_only(folder: Path, step: Path, state: dict[str, Any]) -> None:
    """Name ``step``, a whole checkpoint folder in ``folder``, as the one in force (``state.json``, with ``state``), then
    remove the others: a kill before the name is written leaves the previous checkpoint in force."""
    atomic_write_text(folder / "state.json", json.dumps({**state, "step": step.name}))
    for old in folder.glob("step_*"):
        if old != step:
            shutil.rmtree(old, ignore_errors=True)


def _random_state() -> dict[str, Any]:
    state = {"torch": th.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if th.cuda.is_available():
        state["cuda"] = th.cuda.get_rng_state_all()
    return state


def _set_random_state(state: dict[str, Any]) -> None:
    th.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if "cuda" in state and th.cuda.is_available():
        th.cuda.set_rng_state_all(state["cuda"])


class TrainingCheckpoint(BaseCallback):
    """Saves the seed's training every :data:`CHECKPOINT_SECONDS` into ``folder`` (a folder ``step_<k>`` per checkpoint,
    named by ``state.json`` once whole, so a kill during a save leaves the previous one in force).

    :param folder: the seed's checkpoint folder
    :param curve: the seed's curve, if any (its points and best weights are part of the checkpoint)
    :param record: the seed's record so far (the untrained return, the machine)
    :param seconds: the training seconds of the processes before this one
    """

    def __init__(
        self, folder: Path, curve: Curve | None = None, record: dict[str, Any] | None = None, seconds: float = 0.0
    ) -> None:
        super().__init__()
        self.folder, self.curve, self.record, self.seconds = folder, curve, record or {}, seconds
        self.started = self.last = time.perf_counter()

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:  # after the previous collection's gradient steps, before the next collection
        if time.perf_counter() - self.last >= CHECKPOINT_SECONDS:
            self.save()
            self.last = time.perf_counter()

    def save(self) -> None:
        """Save the training as it stands, as ``step_<env steps>``, and remove the checkpoints before it."""
        model: Any = self.model
        step = self.folder / f"step_{model.num_timesteps}"
        model.save(step / "model.zip")  # its last observations and episode starts too
        if hasattr(model, "replay_buffer"):  # an on-policy model's rollout buffer is empty before a collection
            model.save_replay_buffer(step / "buffer.pkl")
        with atomic_path(step / "state.pt") as tmp:
            th.save(
                {
                    "env": pickle.dumps(model.get_env()),  # the envs mid-episode, their random generators with them
                    "random": _random_state(),
                    "curve": None
                    if self.curve is None
                    else (self.curve.points, self.curve.best, self.curve.best_step, self.curve.seconds),
                },
                tmp,
            )
        seconds = self.seconds + time.perf_counter() - self.started
        atomic_write_text(step / "record.json", json.dumps({"record": self.record, "train_seconds": seconds}))
        keep_only(self.folder, step, {})


def resume_training(
    folder: Path, curve: Curve | None, device: str, algorithm: Any = None
) -> tuple[Any, dict[str, Any], float] | None:
    """The model of the last checkpoint in ``folder`` as it was saved, with ``curve`` and the random generators set back
    (call :meth:`learn` next), its record so far and its training seconds; None without a checkpoint.

    :param algorithm: the model's class (default: TwoStageSAC)
    """
    from sb3_taskalloc import TwoStageSAC

    state_file = folder / "state.json"
    if not state_file.is_file():
        return None
    step = folder / json.loads(state_file.read_text())["step"]
    state = th.load(step / "state.pt", weights_only=False)
    algorithm = TwoStageSAC if algorithm is None else algorithm
    model = algorithm.load(step / "model.zip", env=pickle.loads(state["env"]), device=device, force_reset=False)
    if (step / "buffer.pkl").exists():
        model.load_replay_buffer(step / "buffer.pkl")
    if curve is not None:
        curve.points, curve.best, curve.best_step, curve.seconds = state["curve"]
    saved = json.loads((step / "record.json").read_text())
    _set_random_state(state["random"])  # last: loading the model draws from them
    return model, saved["record"], saved["train_seconds"]
