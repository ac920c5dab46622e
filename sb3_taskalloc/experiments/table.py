"""The paper's results table, regenerated.

Rows: train, zero-shot (entity), few-shot (entity), zero-shot (task), few-shot (task). Columns: Ours, GA, PSO, SOS,
W/o Pre (sequence), W/o Pre (random), W/o AMIX, W/o TAM, Greedy, MILP, MaskablePPO. A cell is the mean ± std over
seeds of each seed's mean deterministic return over ``eval_episodes`` seeded evaluation episodes.

- Train: the method trained on ``TaskAlloc/<Env>-v0`` for ``train_steps`` (RL) or run on it (baselines).
- Zero-shot: the trained model on the ``EntityShift`` / ``TaskShift`` preset, no learning (baselines: run there).
- Few-shot: the trained model fine-tuned on the preset for ``few_shot_steps`` (the paper: 200 episodes).
- From scratch: Ours trained on the preset itself with the training budget: the reference of the zero-shot goal
  (zero-shot ≥ 0.8 × from scratch).

Below the table, the goals of the comparison are computed from its means: Ours against the best planner, Greedy and
the W/o Pre rows on the training env, and zero-shot against from scratch on each preset.

Every finished cell is appended to ``cells.csv`` and every trained model saved under ``models/``, so an interrupted
run resumes where it stopped (``--fresh`` starts over).
"""

from __future__ import annotations

import csv
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

#: Planner settings of the ``local`` and ``smoke`` budgets (rollouts per re-plan are what makes them slow).
PLANNER_BUDGET: dict[str, Any] = {"population": 20, "budget": 100}

ROWS = [
    "train",
    "zero-shot (entity)",
    "few-shot (entity)",
    "from scratch (entity)",
    "zero-shot (task)",
    "few-shot (task)",
    "from scratch (task)",
]
#: Columns trained from scratch on the presets (the reference of the zero-shot goal; the others would double the cost).
SCRATCH_METHODS = ("Ours",)
ENVS = ["Almighty", "EPT", "RBF", "MT"]
EPISODE_STEPS = {"Almighty": 1, "EPT": 100, "RBF": 100, "MT": 150}


@dataclass(frozen=True)
class Method:
    """One column: ``kind`` is ``"sac"`` (TwoStageSAC with ``kwargs`` as policy kwargs), ``"ppo"`` (MaskablePPO),
    ``"planner"`` (GA/PSO/SOS class name) or ``"static"`` (Greedy, MILP)."""

    kind: str
    kwargs: dict[str, Any] = field(default_factory=dict)
    target: str = ""

    @property
    def learns(self) -> bool:
        return self.kind in ("sac", "ppo")


METHODS: dict[str, Method] = {
    "Ours": Method("sac"),
    "GA": Method("planner", target="GeneticAlgorithm"),
    "PSO": Method("planner", target="ParticleSwarm"),
    "SOS": Method("planner", target="SymbioticOrganismsSearch"),
    "W/o Pre (sequence)": Method("sac", {"preassign": False, "task_order": "sequential"}),
    "W/o Pre (random)": Method("sac", {"preassign": False, "task_order": "random"}),
    "W/o AMIX": Method("sac", {"mixer": "global"}),
    "W/o TAM": Method("sac", {"encoder": "mlp"}),
    "Greedy": Method("static", target="GreedyAllocator"),
    "MILP": Method("static", target="MILPAllocator"),
    "MaskablePPO": Method("ppo"),
}


@dataclass(frozen=True)
class Budget:
    """Training and evaluation budget of a table run.

    :param train_episodes: training episodes of the RL methods (or per env name)
    :param few_shot_episodes: fine-tuning episodes of the few-shot rows (paper: 200)
    :param eval_episodes: evaluation episodes per seed
    :param planner: GA/PSO/SOS keywords (None: the paper's settings)
    :param sac: extra TwoStageSAC keywords
    :param ppo: extra MaskablePPO keywords
    :param milp: MILPAllocator keywords
    :param max_episode_steps: shorter episodes than the envs' own (training and evaluation), for smoke runs
    """

    train_episodes: int | dict[str, int]
    few_shot_episodes: int
    eval_episodes: int
    planner: dict[str, Any] | None
    sac: dict[str, Any] = field(default_factory=dict)
    ppo: dict[str, Any] = field(default_factory=dict)
    milp: dict[str, Any] = field(default_factory=dict)
    max_episode_steps: int | None = None

    def steps(self, env: str, episodes: int | dict[str, int]) -> int:
        n = episodes[env] if isinstance(episodes, dict) else episodes
        return n * min(self.max_episode_steps or EPISODE_STEPS[env], EPISODE_STEPS[env])

    def make(self, env_id: str) -> gym.Env:
        """The env of a run (episodes cut at ``max_episode_steps`` when set)."""
        return gym.make(env_id, max_episode_steps=self.max_episode_steps) if self.max_episode_steps else gym.make(env_id)


BUDGETS: dict[str, Budget] = {
    # The paper: 1000 training episodes, 200 fine-tuning episodes, 10 evaluation episodes, planners at full settings.
    "paper": Budget(1000, 200, 10, None),
    # A budget for one CPU thread: TwoStageSAC trains at 8-30 env steps/s there, so about an hour per env.
    "local": Budget({"Almighty": 1200, "EPT": 20, "RBF": 20, "MT": 14}, 5, 3, PLANNER_BUDGET, milp={"time_limit": 2.0}),
    # CI: checks the pipeline end to end in seconds; the figures mean nothing.
    "smoke": Budget(
        2,
        1,
        1,
        {"population": 4, "budget": 8, "horizon": 3, "tail": 2},
        sac={"learning_starts": 10, "batch_size": 8, "select_batch_size": 4, "policy_kwargs": {"hidden_dim": 16}},
        ppo={"n_steps": 16, "batch_size": 8, "n_epochs": 1},
        milp={"time_limit": 0.5},
        max_episode_steps=8,
    ),
}

FOOTNOTES = {
    "size": "n/a (size): the method's networks are built for the training env's entity/task counts (encoder='mlp', "
    "mixer='global', MaskablePPO's flat policy); the preset has other counts.",
    "static": "n/a (no learning): the baseline has nothing to fine-tune or train; its zero-shot row is its run on the preset.",
    "scratch": "n/a (scratch): only Ours is trained from scratch on the presets, as the reference of its zero-shot goal.",
    "preset": "n/a (no preset): Almighty has no entity or task shift presets.",
}


def zoo_hyperparameters(env_id: str, path: str | Path | None = None) -> dict[str, Any]:
    """TwoStageSAC keywords of ``env_id`` from ``zoo_configs/two_stage_sac.yml`` (the same values the zoo trains with;
    ``policy`` and ``n_timesteps`` left out); ``{}`` when the file or the block is missing."""
    import yaml

    path = Path(path) if path else Path(__file__).resolve().parents[2] / "zoo_configs" / "two_stage_sac.yml"
    if not path.exists():
        return {}
    block = dict((yaml.safe_load(path.read_text()) or {}).get(env_id, {}))
    block.pop("policy", None)
    block.pop("n_timesteps", None)
    return block


def row_env(env: str, row: str) -> str | None:
    """Env id of a row (None when the env has no such preset)."""
    if row == "train":
        return f"TaskAlloc/{env}-v0"
    if env == "Almighty":
        return None
    return f"TaskAlloc/{env}-{'EntityShift' if 'entity' in row else 'TaskShift'}-v0"


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
        out: str | Path = "results",
        methods: list[str] | None = None,
        progress: bool = True,
    ) -> None:
        if env not in ENVS:
            raise ValueError(f"env must be one of {ENVS}, got {env!r}")
        if budget not in BUDGETS:
            raise ValueError(f"budget must be one of {list(BUDGETS)}, got {budget!r}")
        unknown = set(methods or []) - set(METHODS)
        if unknown:
            raise ValueError(f"unknown methods {sorted(unknown)}; choose from {list(METHODS)}")
        self.env, self.seeds, self.budget_name, self.budget = env, seeds, budget, BUDGETS[budget]
        self.methods = methods or list(METHODS)
        self.folder = Path(out) / env
        self.progress = progress
        self.cells_path = self.folder / "cells.csv"

    # ------------------------------------------------------------ records

    def done(self) -> dict[tuple[str, str, int], str]:
        """Finished cells (method, row, seed) → value ("n/a:<reason>" or a number) from ``cells.csv``."""
        if not self.cells_path.exists():
            return {}
        with self.cells_path.open() as f:
            return {(r["method"], r["row"], int(r["seed"])): r["value"] for r in csv.DictReader(f)}

    def _record(self, method: str, row: str, seed: int, value: str, seconds: float) -> None:
        new = not self.cells_path.exists()
        with self.cells_path.open("a", newline="") as f:
            writer = csv.writer(f)
            if new:
                writer.writerow(["method", "row", "seed", "value", "seconds", "budget"])
            writer.writerow([method, row, seed, value, f"{seconds:.1f}", self.budget_name])

    # ------------------------------------------------------------ models

    def _model_path(self, method: str, seed: int, row: str = "train") -> Path:
        return self.folder / "models" / f"{_slug(method)}_s{seed}_{_slug(row)}.zip"

    def _new_model(self, method: Method, env_id: str, seed: int, log: Path) -> Any:
        from stable_baselines3.common.monitor import Monitor
        from stable_baselines3.common.vec_env import DummyVecEnv

        from sb3_taskalloc import TwoStageSAC

        log.parent.mkdir(parents=True, exist_ok=True)
        if method.kind == "ppo":
            from sb3_contrib import MaskablePPO

            vec = DummyVecEnv([lambda: Monitor(self.budget.make(env_id), filename=str(log))])
            return MaskablePPO("MultiInputPolicy", vec, seed=seed, **self.budget.ppo)
        env = Monitor(self.budget.make(env_id), filename=str(log))
        train_id = row_env(self.env, "train")
        assert train_id is not None
        kwargs = {**zoo_hyperparameters(train_id), **self.budget.sac}  # the training env's settings on the presets too
        policy_kwargs = {**kwargs.pop("policy_kwargs", {}), **method.kwargs}
        return TwoStageSAC("TAMPolicy", env, seed=seed, policy_kwargs=policy_kwargs, **kwargs)

    def _load(self, method: Method, path: Path, env_id: str | None = None, log: Path | None = None) -> Any:
        from stable_baselines3.common.monitor import Monitor

        env = Monitor(self.budget.make(env_id), filename=str(log) if log else None) if env_id else None
        if method.kind == "ppo":
            from sb3_contrib import MaskablePPO

            return MaskablePPO.load(path, env=env)
        from sb3_taskalloc import TwoStageSAC

        return TwoStageSAC.load(path, env=env)

    def trained(self, name: str, seed: int, row: str = "train") -> Any:
        """The model of ``name`` trained from scratch on the env of ``row`` (the train env, or a preset for the
        "from scratch" rows) with the training budget and the train env's hyperparameters (loaded when saved before)."""
        method, env_id = METHODS[name], row_env(self.env, row)
        assert env_id is not None
        path = self._model_path(name, seed, row)
        if path.exists():
            return self._load(method, path)
        suffix = "" if row == "train" else f"_{_slug(row)}"
        model = self._new_model(method, env_id, seed, self.folder / "logs" / f"{_slug(name)}_s{seed}{suffix}.monitor.csv")
        model.learn(self.budget.steps(self.env, self.budget.train_episodes))
        path.parent.mkdir(parents=True, exist_ok=True)
        model.save(path)
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
            return f"{evaluate(agent, env_id, budget, seed, method):.6g}"
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
            if not same_size:
                model.set_env(target)  # the TAM policy adopts the preset's entity/task counts
            return f"{evaluate(model, env_id, budget, seed, method):.6g}"
        path = self._model_path(name, seed, row)
        log = self.folder / "logs" / f"{_slug(name)}_s{seed}_{_slug(row)}.monitor.csv"
        if path.exists():
            tuned = self._load(method, path)
        else:
            tuned = self._load(method, self._model_path(name, seed), env_id, log)
            tuned.learn(self.budget.steps(self.env, self.budget.few_shot_episodes), reset_num_timesteps=False)
            tuned.save(path)
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
        self.plot_curves()
        return self.write_table()

    # ------------------------------------------------------------ outputs

    def write_table(self) -> Path:
        """``table.csv`` (row, method, mean, std, n) and ``table.md`` (mean ± std, n/a with footnotes)."""
        done = self.done()
        notes: set[str] = set()
        summary: dict[tuple[str, str], str] = {}
        with (self.folder / "table.csv").open("w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["row", "method", "mean", "std", "n"])
            for row in ROWS:
                for name in self.methods:
                    values = [done[(name, row, s)] for s in range(self.seeds) if (name, row, s) in done]
                    numbers = [float(v) for v in values if not v.startswith("n/a")]
                    if numbers:
                        mean, std = float(np.mean(numbers)), float(np.std(numbers))
                        writer.writerow([row, name, f"{mean:.4f}", f"{std:.4f}", len(numbers)])
                        summary[(row, name)] = f"{mean:.1f} ± {std:.1f}" if len(numbers) > 1 else f"{mean:.1f}"
                    elif values:
                        key = values[0].split(":", 1)[1]
                        notes.add(key)
                        writer.writerow([row, name, "n/a", key, 0])
                        summary[(row, name)] = f"n/a ({key})"
        lines = [
            f"# {self.env}: return, mean ± std over {self.seeds} seeds (budget `{self.budget_name}`)"
            if self.seeds > 1
            else f"# {self.env}: return of one seed (budget `{self.budget_name}`)",
            "",
            f"Command: `python -m sb3_taskalloc.experiments table --env {self.env} --seeds {self.seeds} --budget "
            f"{self.budget_name}`. Budget: {self.budget}.",
            "",
            "| setting | " + " | ".join(self.methods) + " |",
            "|---|" + "---|" * len(self.methods),
        ]
        for row in ROWS:
            cells = [summary.get((row, name), "") for name in self.methods]
            if any(c and "(preset)" not in c for c in cells):
                lines.append(f"| {row} | " + " | ".join(cells) + " |")
        lines += ["", *[f"- {FOOTNOTES[k]}" for k in sorted(notes - {"preset"})]]
        goals = self.goals()
        if goals:
            lines += ["", "Goals (ratios of the means above; higher is better):", "", *[f"- {g}" for g in goals]]
        path = self.folder / "table.md"
        path.write_text("\n".join(lines) + "\n")
        return path

    def means(self) -> dict[tuple[str, str], float]:
        """(row, method) → mean over the finished seeds below ``seeds`` (numbers only), as in the table: cells of
        further seeds in ``cells.csv`` (a run with more seeds) do not enter a table of fewer."""
        done = self.done()
        out: dict[tuple[str, str], float] = {}
        for row in ROWS:
            for name in self.methods:
                numbers = [
                    float(v)
                    for (m, r, s), v in done.items()
                    if m == name and r == row and s < self.seeds and not v.startswith("n/a")
                ]
                if numbers:
                    out[(row, name)] = float(np.mean(numbers))
        return out

    def goals(self) -> list[str]:
        """The comparison's goals, as text lines: Ours / best of GA, PSO, SOS (goal ≥ 1.1), Ours / Greedy (≥ 1), Ours
        against both W/o Pre rows (above), and zero-shot / from scratch on each preset (≥ 0.8)."""
        mean = self.means()
        ours = mean.get(("train", "Ours"))
        lines: list[str] = []
        if ours is None:
            return lines

        def ratio(a: float, b: float) -> str:
            """Ours a against the reference b, higher is better: a / b for positive returns; for negative returns
            (MT's are net costs) the reference's cost over Ours' cost, b / a; with mixed signs only the difference."""
            if b > 0:
                return f"{a / b:.3f}"
            if b < 0 and a < 0:
                return f"{b / a:.3f} (negative returns: reference cost / Ours' cost)"
            return f"n/a (signs differ: difference {a - b:+.1f})"

        planners = {m: mean[("train", m)] for m in ("GA", "PSO", "SOS") if ("train", m) in mean}
        if planners:
            best = max(planners, key=planners.__getitem__)
            lines.append(f"Ours / best planner ({best}) on the training env: {ratio(ours, planners[best])} (goal ≥ 1.1)")
        if ("train", "Greedy") in mean:
            lines.append(f"Ours / Greedy on the training env: {ratio(ours, mean[('train', 'Greedy')])} (goal ≥ 1)")
        for m in ("W/o Pre (sequence)", "W/o Pre (random)"):
            if ("train", m) in mean:
                lines.append(f"Ours − {m} on the training env: {ours - mean[('train', m)]:+.1f} (goal > 0)")
        for shift in ("entity", "task"):
            zero, scratch = mean.get((f"zero-shot ({shift})", "Ours")), mean.get((f"from scratch ({shift})", "Ours"))
            if zero is not None and scratch is not None:
                lines.append(f"Ours zero-shot / from scratch on the {shift} shift: {ratio(zero, scratch)} (goal ≥ 0.8)")
        return lines

    def plot_curves(self) -> Path | None:
        """``curves.png``: training episode returns of the RL methods, averaged over seeds (from the Monitor logs)."""
        from sb3_taskalloc.experiments.plots import plot_learning_curve

        curves: dict[str, np.ndarray] = {}
        for name in self.methods:
            runs = []
            for seed in range(self.seeds):
                log = self.folder / "logs" / f"{_slug(name)}_s{seed}.monitor.csv"
                if log.exists():
                    rows = log.read_text().strip().splitlines()[2:]  # Monitor: a JSON line, then the header
                    runs.append(np.array([float(r.split(",")[0]) for r in rows]))
            if runs and min(len(r) for r in runs) > 0:
                n = min(len(r) for r in runs)
                curves[name] = np.mean([r[:n] for r in runs], axis=0)
        if not curves:
            return None
        return plot_learning_curve(
            curves, self.folder / "curves.png", title=f"{self.env}: training episodes ({self.budget_name})"
        )
