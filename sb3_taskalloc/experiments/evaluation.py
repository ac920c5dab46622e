"""Evaluation shared by the experiments: held-out, validation and fingerprint episodes, deterministic returns, the
learning curve callback, and the worker set-up of runs that train seeds in parallel."""

from __future__ import annotations

import copy
import hashlib
import json
import os
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from sb3_taskalloc.common.utils import atomic_write_text
from sb3_taskalloc.experiments.budgets import PLANNER_BUDGET, config_key, env_settings

#: Planners run at the experiments' budget (rollouts per re-plan are what makes them slow).
PLANNERS = ("GeneticAlgorithm", "ParticleSwarm", "SymbioticOrganismsSearch")


def seed_mean(records: list[dict[str, Any]], name: str) -> tuple[float, int]:
    """Mean of figure ``name`` over the seeds where it is defined, and their number: a seed whose sampled decisions
    never differ has no corr(ΔQ, ΔḠ) (NaN), which must not make the mean NaN nor count as a value."""
    values = np.array([r[name] for r in records], dtype=float)
    defined = values[~np.isnan(values)]
    return (float(defined.mean()) if defined.size else float("nan")), int(defined.size)


#: Held-out reset seeds reserved for each training seed: 10,000 + 100·seed + k for k below this.
EPISODES_PER_SEED = 100


def eval_seeds(seed: int, episodes: int) -> list[int]:
    """Reset seeds of the held-out evaluation episodes of training seed ``seed`` (disjoint from training seeds)."""
    return [10_000 + EPISODES_PER_SEED * seed + k for k in range(episodes)]


def validation_seeds(seed: int, episodes: int) -> list[int]:
    """Reset seeds of the validation episodes of training seed ``seed``, which pick the best checkpoint
    (``LearnRun(validation_episodes)``): disjoint from the training seeds and from every held-out evaluation episode."""
    return [30_000 + 100 * seed + k for k in range(episodes)]


def episode_returns(
    agent: Any,
    env_id: str,
    seeds: list[int],
    planner: Callable[[gym.Env], Any] | None = None,
    progress: str | None = None,
) -> list[float]:
    """Deterministic return of ``agent`` (anything with SB3's ``predict``) on one episode per reset seed.

    :param planner: builds the agent from the episode's env instead (the planners act in the env they clone)
    :param progress: a progress bar over the episodes, with this label (None: none)
    """
    from tqdm.auto import tqdm

    returns = []
    for s in tqdm(seeds, desc=progress, disable=progress is None):
        env = gym.make(env_id)
        obs, _ = env.reset(seed=s)
        actor = planner(env) if planner is not None else agent
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(actor.predict(obs, deterministic=True)[0])
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
    return returns


#: Reset seeds of the states whose decisions fingerprint a policy and its searches (:func:`decision_digest`); no
#: figure is measured on them.
FINGERPRINT_SEEDS = (90_000, 90_001)


def decision_digest(agent: Any, env_id: str, seeds: Iterable[int] = FINGERPRINT_SEEDS) -> str:
    """Digest of ``agent``'s deterministic actions in the first state of each episode of ``seeds``, with torch's random
    state forked at a fixed seed (the sampled searches draw the same, and the caller's draws are untouched)."""
    import torch as th

    digest = hashlib.sha256()
    with th.random.fork_rng():
        th.manual_seed(0)
        for s in seeds:
            obs, _ = gym.make(env_id).reset(seed=s)
            digest.update(np.asarray(agent.predict(obs, deterministic=True)[0], dtype=np.int64).tobytes())
    return digest.hexdigest()[:16]


def machine() -> dict[str, Any]:
    """The machine and libraries a figure was measured with. A seed's training repeats to the digit in one venv on one
    machine, and seeds measured on other days have moved without a cause found (docs/learning.md, "The plain
    constructor's first experience"): a comparison of two records starts here. The vector instructions torch's
    kernels use are among them, as they round batched products differently."""
    import platform
    from importlib import metadata

    import torch as th

    def version(dist: str) -> str | None:
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return None

    cpuinfo = Path("/proc/cpuinfo").read_text().splitlines() if Path("/proc/cpuinfo").exists() else []
    models = [line.split(":", 1)[1].strip() for line in cpuinfo if line.startswith("model name")]
    return {
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpu": models[0] if models else platform.processor() or None,
        "cpu_capability": th.backends.cpu.get_cpu_capability(),  # the vector instructions torch's kernels use
        "cpus": os.cpu_count(),
        "numpy": np.__version__,
        "torch": th.__version__,
        "gpu": th.cuda.get_device_name() if th.cuda.is_available() else None,
        "libraries": {dist: version(dist) for dist in ("stable-baselines3", "gymnasium", "scipy")},
    }


def one_thread(parent: int) -> None:
    """Worker set-up of ``LearnRun.run(jobs > 1)``: one torch thread per process, the TaskAlloc ids registered, and a
    watch that ends the worker when the process that started it is gone (:func:`exit_with_parent`).

    :param parent: the pid of the process that started the pool (``os.getpid()`` there). A worker reads its own parent
        only after its interpreter has started and imported torch, seconds later; a parent killed in between would
        leave it re-parented already, watching the wrong process
    """
    import threading

    import torch as th

    th.set_num_threads(1)
    threading.Thread(target=exit_with_parent, args=(parent,), daemon=True).start()


def exit_with_parent(parent: int, poll: float = 1.0) -> None:
    """Exit this process once its parent ``parent`` is gone (it is then re-parented). A ``learn --jobs N`` stopped by a
    signal its workers do not receive (``kill``, the session ending) would otherwise leave them training unobserved,
    writing seeds into the results folder while a new run of the same folder starts. Seed records are written
    atomically, so the seed in progress loses only its unsaved work, as on Ctrl-C; a new run resumes from the finished
    seeds."""
    while os.getppid() == parent:
        time.sleep(poll)
    os._exit(1)


class Curve(BaseCallback):
    """Deterministic return on ``seeds``' episodes every ``every`` env steps (and at step 0).

    :param keep_best: also keep a copy of the policy's weights at the best evaluation after step 0 (``best``, at
        ``best_step``), as SB3's ``EvalCallback(best_model_save_path=...)`` keeps the best model
    """

    def __init__(self, env_id: str, seeds: list[int], every: int, keep_best: bool = False) -> None:
        super().__init__()
        self.env_id, self.seeds, self.every, self.keep_best = env_id, seeds, every, keep_best
        self.points: list[tuple[int, float]] = []
        self.best: dict[str, Any] | None = None
        self.best_step = 0
        #: Wall-clock seconds spent in the evaluations: the experiment's cost, not training's.
        self.seconds = 0.0

    def _evaluate(self) -> None:
        self.evaluate_at(self.num_timesteps)

    def evaluate_at(self, step: int) -> None:
        """Add the point of ``step`` (training that goes on outside ``learn``, e.g. DAgger's rollouts, counts its own)."""
        t0 = time.perf_counter()
        value = float(np.mean(episode_returns(self.model, self.env_id, self.seeds)))
        self.seconds += time.perf_counter() - t0
        if self.keep_best and step > 0 and value > max((v for t, v in self.points if t > 0), default=-np.inf):
            self.best = copy.deepcopy(self.model.policy.state_dict())
            self.best_step = step
        self.points.append((step, value))

    def _on_training_start(self) -> None:
        if not self.points:  # a curve resumed from a checkpoint has its points, step 0's among them
            self._evaluate()

    def _on_step(self) -> bool:
        # With n_envs envs the step count grows by n_envs per call: evaluate on passing each multiple of `every`.
        if self.num_timesteps // self.every > (self.num_timesteps - self.training_env.num_envs) // self.every:
            self._evaluate()
        return True


def baseline_returns(run: Any, seed: int) -> dict[str, Any]:
    """Greedy, the per-step MILP and the planners on seed ``seed``'s evaluation episodes. They depend on the env,
    the episodes and their own budgets only, so they are filed under a digest of those and shared by every run of
    the algorithm's settings (each is computed once)."""
    from sb3_taskalloc import baselines as b

    seeds = eval_seeds(seed, run.eval_episodes)
    key = config_key(env_settings(run.env_id), seeds, ("milp_node_limit", run.milp_node_limit), PLANNER_BUDGET)
    path = Path(run.out) / run.env / f"baselines_seed_{seed}_{key}.json"
    done: dict[str, Any] = json.loads(path.read_text()) if path.exists() else {}

    def bar(name: str) -> str | None:  # the per-step MILP takes minutes on RBF: a bar where the run shows them
        return f"{run.env} seed {seed}: {name}" if run.progress_bars else None

    def milp_returns() -> list[float]:
        milp = b.MILPAllocator.reference(run.milp_node_limit)
        returns = episode_returns(milp, run.env_id, seeds, progress=bar("per-step MILP"))
        done["MILP gap"] = milp.gap_summary()  # how far from optimal its allocations may be, filed beside them
        return returns

    agents: dict[str, Callable[[], list[float]]] = {
        "Greedy": lambda: episode_returns(b.GreedyAllocator(), run.env_id, seeds),
        "MILP": milp_returns,
    }
    for name in run.planners:
        cls = getattr(b, name)

        def planner(env: gym.Env, cls: Any = cls) -> Any:
            return cls(env, seed=seed, **PLANNER_BUDGET)

        agents[name] = lambda planner=planner, name=name: episode_returns(  # type: ignore[misc]
            None, run.env_id, seeds, planner, progress=bar(name)
        )
    for name, evaluate in agents.items():
        if name not in done:
            done[name] = evaluate()
            atomic_write_text(path, json.dumps(done) + "\n")
    return {name: done[name] for name in (*agents, "MILP gap") if name in done}
