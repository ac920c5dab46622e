"""The paper's results table, regenerated.

Rows: train, zero-shot (entity), few-shot (entity), zero-shot (task), few-shot (task). Columns: Ours, GA, PSO, SOS,
W/o Pre (sequence), W/o Pre (random), W/o AMIX, W/o TAM, Greedy, MILP, MaskablePPO. A cell is the mean ± std over
seeds of each seed's mean deterministic return over ``eval_episodes`` seeded evaluation episodes.

- Train: the method trained on ``TaskAlloc/<Env>-v0`` for ``train_steps`` (RL) or run on it (baselines); a zoo block's
  ``SelectDAggerCallback`` runs after the training steps of the TwoStageSAC columns that pre-assign.
- Zero-shot: the trained model on the ``EntityShift`` / ``TaskShift`` preset, no learning (baselines: run there).
- Few-shot: the trained model fine-tuned on the preset for ``few_shot_steps`` (the paper: 200 episodes).
- From scratch: Ours trained on the preset itself with the training budget: the reference of the zero-shot goal
  (zero-shot ≥ 0.8 × from scratch).

Below the table, the goals of the comparison are computed from its means: Ours against the best planner, Greedy and
the W/o Pre rows on the training env, and zero-shot against from scratch on each preset.

Every finished cell is appended to ``cells.csv`` and every trained model saved under ``models/``, both filed under a
digest of the configuration that produced them (budget, env settings, method, hyperparameters): an interrupted run
resumes where it stopped, and a run with other settings never shows or reuses them (``--fresh`` starts over).
"""

from __future__ import annotations

import csv
import io
import os
import pickle
import shutil
import time
import zipfile
from collections.abc import Callable
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from sb3_taskalloc.common.utils import atomic_path, check_choices
from sb3_taskalloc.experiments import checkpoint, table_report
from sb3_taskalloc.experiments.budgets import (
    BUDGETS,
    DAGGER_BUDGET,
    ENVS,
    METHODS,
    ROWS,
    SCRATCH_METHODS,
    Budget,
    Method,
    code_defaults,
    config_key,
    env_settings,
    row_env,
)
from sb3_taskalloc.experiments.table_report import env_logs
from sb3_taskalloc.zoo_config import merge_settings, zoo_dagger, zoo_hyperparameters


def seeded_vec_env(env: Any, seed: int) -> Any:
    """``env`` as a VecEnv whose next reset (``load``'s ``set_env``) takes ``seed``."""
    from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

    vec = env if isinstance(env, VecEnv) else DummyVecEnv([lambda: env])
    vec.seed(seed)
    return vec


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name).strip("_").lower()


def evaluate(
    agent: Any, env_id: str, budget: Budget, seed: int, method: Method, make_planner: Callable | None = None
) -> float:
    """Mean deterministic return over the budget's seeded evaluation episodes of ``env_id``."""
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv

    episodes = budget.eval_episodes
    vec = DummyVecEnv([lambda: Monitor(budget.make(env_id))])
    vec.seed(10_000 + seed)
    if make_planner is not None:
        agent = make_planner(vec.envs[0])
    if method.kind == "ppo":
        from sb3_contrib.common.maskable.evaluation import evaluate_policy as maskable_evaluate

        returns, _ = maskable_evaluate(agent, vec, n_eval_episodes=episodes, deterministic=True, return_episode_rewards=True)
    else:
        from stable_baselines3.common.evaluation import evaluate_policy

        returns, _ = evaluate_policy(agent, vec, n_eval_episodes=episodes, deterministic=True, return_episode_rewards=True)
    vec.close()
    return float(np.mean(returns))


class TableRun:
    """One env's table: trains, evaluates, records and resumes.

    :param env: ``"Almighty"``, ``"EPT"``, ``"RBF"`` or ``"MT"``
    :param seeds: number of seeds (0 .. seeds − 1)
    :param budget: a :data:`BUDGETS` name
    :param out: results folder (the table goes to ``out/<env>/``)
    :param methods: columns to run (default: all)
    :param progress: show a progress bar
    """

    def __init__(
        self,
        env: str,
        seeds: int,
        budget: str,
        out: str | Path = "runs/tables",
        methods: list[str] | None = None,
        progress: bool = True,
    ) -> None:
        check_choices({"env": (env, tuple(ENVS)), "budget": (budget, tuple(BUDGETS))})
        unknown = set(methods or []) - set(METHODS)
        if unknown:
            raise ValueError(f"unknown methods {sorted(unknown)}; choose from {list(METHODS)}")
        self.env, self.seeds, self.budget_name, self.budget = env, seeds, budget, BUDGETS[budget]
        self.methods = methods or list(METHODS)
        self.folder = Path(out) / env
        self.progress = progress
        self.cells_path = self.folder / "cells.csv"

    # ------------------------------------------------------------ records

    def _train_settings(self, name: str, row: str = "train") -> list[Any]:
        """Everything that changes the model of ``name`` trained on the env of ``row``."""
        method, budget = METHODS[name], self.budget
        learner = budget.sac if method.kind == "sac" else budget.ppo if method.kind == "ppo" else None
        zoo = self._zoo if method.kind == "sac" else None
        steps = budget.steps(self.env, budget.train_episodes)
        settings: list[Any] = [method, env_settings(row_env(self.env, row)), steps, learner, budget.max_episode_steps, zoo]
        if dagger := self._dagger(method):  # appended only when set: the digests of runs without it stay valid
            settings.append(("dagger", dagger))
        if method.kind == "sac":  # what the configuration leaves to the code's defaults changes the model too
            settings.append(("code", code_defaults()))
        return settings

    def cell_key(self, name: str, row: str) -> str:
        """The configuration a cell of ``name`` in ``row`` was computed under (see :func:`.budgets.config_key`)."""
        return config_key(self._train_settings(name), env_settings(row_env(self.env, row)), self.budget)

    def _read_cells(self) -> list[dict[str, str]]:
        """The rows of ``cells.csv``. A last line cut mid-row (a kill while appending) is dropped from the file first."""
        if not self.cells_path.exists():
            return []
        text = self.cells_path.read_text()
        if text and not text.endswith("\n"):
            text = text[: text.rfind("\n") + 1]
            with atomic_path(self.cells_path) as tmp:
                tmp.write_text(text)
        rows = list(csv.DictReader(text.splitlines()))
        return [r for r in rows if None not in r.values() and None not in r]

    def done(self) -> dict[tuple[str, str, int], str]:
        """Finished cells (method, row, seed) → value ("n/a:<reason>" or a number) from ``cells.csv``, computed under
        this run's configuration (cells of other budgets, env settings or hyperparameters are left out)."""
        keys: dict[tuple[str, str], str] = {}
        cells = {}
        for r in self._read_cells():
            if r["method"] not in METHODS or r["row"] not in ROWS:
                continue
            key = keys.setdefault((r["method"], r["row"]), self.cell_key(r["method"], r["row"]))
            if r.get("config") == key:
                cells[(r["method"], r["row"], int(r["seed"]))] = r["value"]
        return cells

    def _record(self, method: str, row: str, seed: int, value: str, seconds: float) -> None:
        """Append one cell (one write of one line), adding the ``config`` column to a file written without it."""
        header = ["method", "row", "seed", "value", "seconds", "budget", "config"]
        self.cells_path.parent.mkdir(parents=True, exist_ok=True)
        rows = self._read_cells()
        if rows and "config" not in rows[0]:
            with atomic_path(self.cells_path) as tmp, tmp.open("w", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=header)
                writer.writeheader()
                writer.writerows({**r, "config": ""} for r in rows)
        line = [method, row, seed, value, f"{seconds:.1f}", self.budget_name, self.cell_key(method, row)]
        new = not self.cells_path.exists()
        buffer = io.StringIO()
        out = csv.writer(buffer)
        if new:
            out.writerow(header)
        out.writerow(line)
        with self.cells_path.open("a", newline="") as f:
            f.write(buffer.getvalue())

    # ------------------------------------------------------------ models

    def _model_path(self, method: str, seed: int, row: str = "train") -> Path:
        """Where a model is saved: named by method, seed, row and the digest of its training configuration."""
        if row.startswith("few-shot"):
            few = self.budget.steps(self.env, self.budget.few_shot_episodes)
            key = config_key(self._train_settings(method), env_settings(row_env(self.env, row)), few)
        else:
            key = config_key(self._train_settings(method, row))
        return self.folder / "models" / f"{_slug(method)}_s{seed}_{_slug(row)}_{key}.zip"

    def _log_path(self, method: str, seed: int, row: str = "train") -> Path:
        """The Monitor log of training a model: named like the model, so logs of other settings are kept apart. With
        ``n_envs`` > 1 each env logs to its own file beside it (:func:`env_logs`)."""
        return self.folder / "logs" / f"{self._model_path(method, seed, row).stem}.monitor.csv"

    @cached_property
    def _zoo(self) -> dict[str, Any]:
        """The training env's block of ``zoo_configs/two_stage_sac.yml``, read once per run."""
        return zoo_hyperparameters(self._train_id)

    def _dagger(self, method: Method) -> dict[str, Any]:
        """The :class:`~sb3_taskalloc.SelectDAggerCallback` keywords a column trains with: the training env's zoo block's
        (:func:`.budgets.zoo_dagger`) under :data:`.budgets.DAGGER_BUDGET`'s for this budget, for the TwoStageSAC
        columns that pre-assign (the W/o Pre columns share one pool of entities, which DAgger cannot teach); ``{}``:
        none."""
        zoo = self._zoo_dagger
        if (
            not zoo
            or method.kind != "sac"
            or not {**self._zoo.get("policy_kwargs", {}), **method.kwargs}.get("preassign", True)
        ):
            return {}
        return {**zoo, **DAGGER_BUDGET.get(self.budget_name, {})}

    @property
    def _train_id(self) -> str:
        """The id of the env the "train" row trains on (the zoo blocks are its)."""
        train_id = row_env(self.env, "train")
        assert train_id is not None
        return train_id

    @cached_property
    def _zoo_dagger(self) -> dict[str, Any]:
        """The training env's zoo block's DAgger callback keywords (:func:`.budgets.zoo_dagger`), read once per run."""
        return zoo_dagger(self._train_id)

    def _sac_kwargs(self) -> dict[str, Any]:
        """TwoStageSAC keywords of every column and row: the training env's zoo block (on the presets too) under the
        budget's own."""
        return merge_settings(self._zoo, self.budget.sac)

    def _n_envs(self, method: Method) -> int:
        """Envs a column collects from at once: ``n_envs`` of :meth:`_sac_kwargs` (rl-zoo3's key) for TwoStageSAC."""
        return int(self._sac_kwargs().get("n_envs", 1)) if method.kind == "sac" else 1

    def _train_env(self, env_id: str, log: Path, n_envs: int) -> Any:
        """A Monitor-wrapped env of ``env_id`` logging to ``log``, or with ``n_envs`` > 1 a DummyVecEnv of them (a
        checkpoint of the training can hold them: :class:`.checkpoint.ResumableMonitor`)."""
        from stable_baselines3.common.vec_env import DummyVecEnv

        from sb3_taskalloc.experiments.checkpoint import ResumableMonitor

        if n_envs == 1:
            return ResumableMonitor(self.budget.make(env_id), filename=str(log))

        def make(path: Path) -> Callable[[], Any]:
            return lambda: ResumableMonitor(self.budget.make(env_id), filename=str(path))

        return DummyVecEnv([make(path) for path in env_logs(log, n_envs)])

    @staticmethod
    def _save(model: Any, path: Path) -> None:
        with atomic_path(path) as tmp:
            model.save(tmp)

    @staticmethod
    def _algorithm(method: Method) -> Any:
        """The class of ``method``'s models: MaskablePPO or TwoStageSAC."""
        from sb3_contrib import MaskablePPO

        from sb3_taskalloc import TwoStageSAC

        return MaskablePPO if method.kind == "ppo" else TwoStageSAC

    def _new_model(self, method: Method, env_id: str, seed: int, log: Path) -> Any:
        from stable_baselines3.common.vec_env import DummyVecEnv

        from sb3_taskalloc import TwoStageSAC
        from sb3_taskalloc.experiments.checkpoint import ResumableMonitor
        from sb3_taskalloc.two_stage_sac.policies import starts_at_rule

        log.parent.mkdir(parents=True, exist_ok=True)
        if method.kind == "ppo":
            from sb3_contrib import MaskablePPO

            vec = DummyVecEnv([lambda: ResumableMonitor(self.budget.make(env_id), filename=str(log))])
            return MaskablePPO("MultiInputPolicy", vec, seed=seed, **self.budget.ppo)
        kwargs = self._sac_kwargs()
        env = self._train_env(env_id, log, int(kwargs.pop("n_envs", 1)))
        policy_kwargs = {**kwargs.pop("policy_kwargs", {}), **method.kwargs}
        if not policy_kwargs.get("preassign", True):
            # W/o Pre decodes the tasks from one shared pool: their teams cannot be searched one task at a time (detail 18).
            kwargs["select_kwargs"] = {**kwargs.get("select_kwargs", {}), "search_coef": 0.0}
        if not starts_at_rule(policy_kwargs):
            # An actor that starts at random weights (W/o TAM) learns even where the block holds the rule's (detail 23).
            kwargs.pop("train_preassign_actor", None)
        return TwoStageSAC("TAMPolicy", env, seed=seed, policy_kwargs=policy_kwargs, **kwargs)

    def _load(
        self, method: Method, path: Path, env_id: str | None = None, log: Path | None = None, seed: int | None = None
    ) -> Any:
        """The model saved at ``path``, with a training env of ``env_id`` logging to ``log`` when given. With ``seed``
        the env's first reset, the sampling and the network updates after loading are seeded (the few-shot training)."""
        env = self._train_env(env_id, log, self._n_envs(method)) if env_id and log else None
        env = seeded_vec_env(env, seed) if env is not None and seed is not None else env
        model = self._algorithm(method).load(path, env=env)
        if seed is not None:
            model.set_random_seed(seed)
        return model

    def _load_saved(self, method: Method, path: Path) -> Any:
        """The model saved at ``path``, or None when there is none. A file that cannot be loaded (cut short by a crash
        outside this runner, say) is moved to ``<name>.broken-<time>.zip``, kept, and the model is trained again."""
        if not path.exists():
            return None
        try:
            return self._load(method, path)
        except (ValueError, zipfile.BadZipFile, EOFError, KeyError, RuntimeError, pickle.UnpicklingError) as error:
            aside = path.with_name(f"{path.stem}.broken-{time.strftime('%Y%m%d-%H%M%S')}.zip")
            os.replace(path, aside)
            print(f"warning: {path} could not be loaded ({error}); moved it to {aside} and computing it again")
            return None

    def trained(self, name: str, seed: int, row: str = "train") -> Any:
        """The model of ``name`` trained from scratch on the env of ``row`` (the train env, or a preset for the
        "from scratch" rows) with the training budget and the train env's hyperparameters (loaded when saved before)."""
        method, env_id = METHODS[name], row_env(self.env, row)
        assert env_id is not None
        path = self._model_path(name, seed, row)
        saved = self._load_saved(method, path)
        if saved is not None:
            shutil.rmtree(checkpoint.training_folder(path), ignore_errors=True)  # left by a kill after the model's save
            return saved
        dagger = self._dagger(method)
        callbacks: list[Any] = []
        if dagger:  # the zoo's schedule: the training steps, then the DAgger of the pointer
            from sb3_taskalloc import SelectDAggerCallback
            from sb3_taskalloc.two_stage_sac.decoding import recommended_decoder

            if dagger.get("teacher") == "recommended":  # the training env's decoder: a preset row may have none
                dagger = {**dagger, "teacher": recommended_decoder(self._train_id)}
            callbacks.append(SelectDAggerCallback(**dagger))
        steps = self.budget.steps(self.env, self.budget.train_episodes)
        return self._learn_resumably(
            method, path, lambda: self._new_model(method, env_id, seed, self._log_path(name, seed, row)), steps, callbacks
        )

    def _learn_resumably(
        self, method: Method, path: Path, start: Callable[[], Any], steps: int, callbacks: list[Any] | None = None
    ) -> Any:
        """``steps`` env steps of training of the model ``start`` makes, checkpointed (:mod:`.checkpoint`; the
        checkpoint's record holds the step the training ends at), then saved at ``path``. A training that a kill stopped
        goes on from its last checkpoint, exactly.

        :param callbacks: callbacks of the training besides the checkpoints (DAgger after it)
        """
        folder = checkpoint.training_folder(path)
        resumed = checkpoint.resume_training(folder, None, "auto", self._algorithm(method))
        if resumed is not None:
            model, record, _ = resumed
        else:
            model = start()
            record = {"end": model.num_timesteps + steps}
        saving = checkpoint.TrainingCheckpoint(folder, record=record)
        model.learn(record["end"] - model.num_timesteps, callback=[saving, *(callbacks or [])], reset_num_timesteps=False)
        self._save(model, path)
        shutil.rmtree(folder, ignore_errors=True)
        return model

    # ------------------------------------------------------------ cells

    def cell(self, name: str, row: str, seed: int) -> str:
        """Compute one cell: a number as text, or ``n/a:<footnote key>``."""
        method = METHODS[name]
        env_id = row_env(self.env, row)
        if env_id is None:
            return "n/a:preset"
        budget = self.budget
        if not method.learns:
            if row.startswith(("few-shot", "from scratch")):
                return "n/a:static"
            from sb3_taskalloc import baselines

            cls = getattr(baselines, method.target)
            if method.kind == "planner":
                planner_kwargs = self.budget.planner or {}
                return f"{evaluate(None, env_id, budget, seed, method, lambda e: cls(e, seed=seed, **planner_kwargs)):.6g}"
            agent = cls(**budget.milp) if method.target == "MILPAllocator" else cls()
            value = f"{evaluate(agent, env_id, budget, seed, method):.6g}"
            table_report.record_milp_gap(self, name, row, seed, agent)  # how far from optimal the MILP's cell may be
            return value
        if row.startswith("from scratch"):
            if name not in SCRATCH_METHODS:
                return "n/a:scratch"
            return f"{evaluate(self.trained(name, seed, row), env_id, budget, seed, method):.6g}"
        model = self.trained(name, seed)
        if row == "train":
            return f"{evaluate(model, env_id, budget, seed, method):.6g}"
        target = budget.make(env_id)
        same_size = model.observation_space == target.observation_space and model.action_space == target.action_space
        if not same_size and not (method.kind == "sac" and model.policy.size_agnostic):
            return "n/a:size"
        if row.startswith("zero-shot"):
            if not same_size:  # the TAM policy adopts the preset's entity/task counts (``load`` takes any env count)
                model = type(model).load(self._model_path(name, seed), env=target)
            return f"{evaluate(model, env_id, budget, seed, method):.6g}"
        path = self._model_path(name, seed, row)
        log = self._log_path(name, seed, row)
        tuned = self._load_saved(method, path)
        if tuned is None:
            few_shot = self.budget.steps(self.env, self.budget.few_shot_episodes)
            tuned = self._learn_resumably(
                method, path, lambda: self._load(method, self._model_path(name, seed), env_id, log, seed=seed), few_shot
            )
        return f"{evaluate(tuned, env_id, budget, seed, method):.6g}"

    def run(self) -> Path:
        """Compute every missing cell, then write the table and the curves; :return: the table's Markdown path."""
        from tqdm.auto import tqdm

        self.folder.mkdir(parents=True, exist_ok=True)
        done = self.done()
        todo = [(m, r, s) for s in range(self.seeds) for m in self.methods for r in ROWS if (m, r, s) not in done]
        for name, row, seed in tqdm(todo, desc=f"{self.env} table", disable=not self.progress):
            t0 = time.perf_counter()
            value = self.cell(name, row, seed)
            self._record(name, row, seed, value, time.perf_counter() - t0)
        table_report.plot_curves(self)
        return table_report.write_table(self)

    def write_table(self) -> Path:
        """``table.csv`` and ``table.md`` of the finished cells (:func:`.table_report.write_table`)."""
        return table_report.write_table(self)
