"""The settings of the paper's table: its rows, its columns (methods) and its budgets."""

from __future__ import annotations

import hashlib
import inspect
import json
from dataclasses import asdict, dataclass, field
from functools import cache
from typing import Any

import gymnasium as gym
import numpy as np

#: HiGHS nodes per solve of the experiments' per-step MILP reference. A stop by work instead of the clock: its
#: allocations, and so its figures, are the same on any machine and under any load (a 2 s wall-clock limit gave 165.5
#: and 163.5 on the same RBF episodes in two runs). Measured in docs/benchmarks.md, "The per-step MILP reference".
MILP_NODE_LIMIT = 100

#: MILPAllocator keywords of that reference (:meth:`MILPAllocator.reference`).
MILP_REFERENCE: dict[str, Any] = {"time_limit": float("inf"), "node_limit": MILP_NODE_LIMIT}

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
    "local": Budget({"Almighty": 1200, "EPT": 20, "RBF": 20, "MT": 14}, 5, 3, PLANNER_BUDGET, milp=MILP_REFERENCE),
    # CI: checks the pipeline end to end in seconds; the figures mean nothing.
    "smoke": Budget(
        2,
        1,
        1,
        {"population": 4, "budget": 20, "horizon": 3, "tail": 2},
        sac={
            "learning_starts": 4,
            "batch_size": 8,
            "buffer_size": 1_000,  # a model is built for every cell it evaluates
            "select_kwargs": {"batch_size": 4},
            "policy_kwargs": {"hidden_dim": 16},
        },
        ppo={"n_steps": 16, "batch_size": 8, "n_epochs": 1},
        milp={"time_limit": 0.1, "node_limit": 5},  # HiGHS's root node alone takes seconds on RBF
        max_episode_steps=4,
    ),
}

#: SelectDAggerCallback keywords of a budget over the zoo block's (:func:`zoo_dagger`): the smoke budget checks the
#: table's DAgger phase in seconds.
DAGGER_BUDGET: dict[str, dict[str, Any]] = {"smoke": {"iterations": 1, "episodes": 1, "epochs": 1}}

FOOTNOTES = {
    "size": "n/a (size): the method's networks are built for the training env's entity/task counts (encoder='mlp', "
    "mixer='global', MaskablePPO's flat policy); the preset has other counts.",
    "static": "n/a (no learning): the baseline has nothing to fine-tune or train; its zero-shot row is its run on the preset.",
    "scratch": "n/a (scratch): only Ours is trained from scratch on the presets, as the reference of its zero-shot goal.",
    "preset": "n/a (no preset): Almighty has no entity or task shift presets.",
}


def env_name(text: str) -> str:
    """A command line's env as the experiments name it (``"RBF"``), from either that or its id (``"TaskAlloc/RBF-v0"``):
    every command takes both."""
    return text.removeprefix("TaskAlloc/").removesuffix("-v0")


def full_env_id(text: str) -> str:
    """A command line's env as its registered id (``"TaskAlloc/RBF-v0"``), from either that or its short name."""
    return f"TaskAlloc/{env_name(text)}-v0"


def yaml_mapping(text: str) -> dict[str, Any]:
    """A command-line option's YAML (or JSON) mapping, e.g. ``"{entropy_bonus: mean}"``; anything else is an
    :class:`argparse.ArgumentTypeError` naming the text."""
    import argparse

    import yaml

    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise argparse.ArgumentTypeError(f"not valid YAML: {text!r} ({str(error).splitlines()[0]})") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a YAML mapping, got {text!r}")
    return value


def row_env(env: str, row: str) -> str | None:
    """Env id of a row (None when the env has no such preset)."""
    if row == "train":
        return f"TaskAlloc/{env}-v0"
    if env == "Almighty":
        return None
    return f"TaskAlloc/{env}-{'EntityShift' if 'entity' in row else 'TaskShift'}-v0"


def config_key(*parts: Any) -> str:
    """A short digest of everything that changes a result (budget, method, env settings, hyperparameters): cells and
    models are filed under it, so results of other settings are never mixed in."""
    text = json.dumps([asdict(p) if hasattr(p, "__dataclass_fields__") else p for p in parts], sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:10]


#: TwoStageSAC's arguments that change how fast it trains, not what it learns on the CPU: left out of
#: :func:`code_defaults`, so that adding one keeps the digests of earlier results (a CUDA run has its own digest).
SPEED_ONLY = ("cuda_graph",)


@cache
def code_defaults() -> dict[str, Any]:
    """What TwoStageSAC's code decides when a configuration leaves it unset: the constructor defaults of TwoStageSAC and
    TAMPolicy and the module constants that shape the initial policy, the select stage and the exact covers. Part of a
    TwoStageSAC result's digest, so a changed default (``RULE_LOGIT_SCALES``, say) files new results apart from old."""
    from sb3_taskalloc import TAMPolicy, TwoStageSAC
    from sb3_taskalloc.common import torch_layers
    from sb3_taskalloc.two_stage_sac import policies, search, select_stage, settings

    def defaults(function: Any) -> dict[str, Any]:
        return {k: p.default for k, p in inspect.signature(function).parameters.items() if p.default is not p.empty}

    constants = {
        "HEURISTIC_INIT": policies.HEURISTIC_INIT,
        "RULE_LOGIT_SCALES": policies.RULE_LOGIT_SCALES,
        "MIXER_DEFAULTS": policies.MIXER_DEFAULTS,
        "SELECT_DEFAULTS": settings.SELECT_DEFAULTS,
        "COVER_TOL": select_stage.COVER_TOL,
        "EXACT_LIMITS": (search.EXACT_NODE_LIMIT, search.EXACT_TIME_LIMIT),
        "PAIR_FEATURE_NAMES": torch_layers.PAIR_FEATURE_NAMES,
    }
    algorithm = {k: v for k, v in defaults(TwoStageSAC.__init__).items() if k not in SPEED_ONLY}
    return {"TwoStageSAC": algorithm, "TAMPolicy": defaults(TAMPolicy.__init__), **constants}


@cache
def env_settings(env_id: str | None) -> dict[str, Any] | None:
    """What defines the env of ``env_id`` (part of a result's configuration): its registration, the settings the built
    env reports (so a changed class default counts too) and a digest of its entity and task tables."""
    if env_id is None:
        return None
    spec = gym.spec(env_id)
    env = gym.make(env_id).unwrapped
    settings = {k: v for k, v in vars(env).items() if not k.startswith("_") and isinstance(v, int | float | str | tuple)}
    tables = hashlib.sha256()
    for table in (getattr(env, "entities", None), getattr(env, "tasks", None)):
        for value in vars(table).values() if table is not None else ():
            if value is not None:
                tables.update(np.ascontiguousarray(value).tobytes())
    env.close()
    return {"id": env_id, "kwargs": spec.kwargs, "max_episode_steps": spec.max_episode_steps, "settings": settings,
            "tables": tables.hexdigest()[:16]}  # fmt: skip
