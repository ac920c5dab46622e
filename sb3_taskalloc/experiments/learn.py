"""Does TwoStageSAC learn? Trained against untrained, Greedy, the per-step MILP and the best planner, per seed.

``python -m sb3_taskalloc.experiments learn --env RBF --seeds 5 --steps 20000`` trains one model per seed and evaluates,
on the same held-out episodes per seed (reset seeds ``10_000 + 100·seed + k``, never a training seed):

- the same policy untrained (its initial rule), and trained;
- the trained policy with only the pre-assign actor learned and with only the pointer learned (the other stage back at
  its initial rule, :func:`~sb3_taskalloc.experiments.diagnose.stage_reset`): which stage's learning the result owes to;
- Greedy, the per-step MILP and the receding-horizon planners (the best of them is reported);
- the critic at the end of training (:func:`~sb3_taskalloc.experiments.diagnose.diagnose`: correlation and scale of Q
  against Monte-Carlo returns).

During training the deterministic return is measured every ``--eval-every`` steps on two held-out episodes (the
curve). With ``--validation-episodes V`` it is measured on V validation episodes instead (reset seeds
``30_000 + 100·seed + k``), and the checkpoint of its best point after step 0 is evaluated on the held-out episodes
beside the final model: the validation episodes choose it, so its held-out return is not selected on the episodes
that report it. Each finished seed is saved to ``<out>/<env>/seed_<k>.json`` under a digest of the settings and skipped when
the command is run again: an interrupted run loses at most the seed in progress. The baselines do not depend on the
algorithm's settings: they are saved per seed under a digest of the env and their own budgets, computed once and shared
by every run with the same ``--out``. The summary goes to ``<out>/<env>.md``,
``.json`` and ``.png``.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import io
import json
import os
import time
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from sb3_taskalloc.common.utils import atomic_write_text, check_counts
from sb3_taskalloc.experiments.budgets import PLANNER_BUDGET, config_key, env_settings, over_zoo, training_env, zoo_dagger

# The DAgger rollouts of training seed ``seed`` run from 50,000 + 1000·seed, clear of the held-out (10,000 + 100·seed),
# validation (30,000 + 100·seed) and diagnosis episodes; SelectDAggerCallback rolls out the same episodes by default.
from sb3_taskalloc.two_stage_sac.callbacks import SelectDAggerCallback, dagger_seed

#: Headers of the critic's figures in the learning tables (:mod:`.diagnose`): against one rollout's return G, against
#: the expected return Ḡ, the correlation a perfect critic would reach against G, with the number of free entities, and
#: its preference between two decisions of a state against their paired branch returns (ΔQ against ΔḠ).
CRITIC_COLUMNS = {
    "q_corr": "corr(Q, G)",
    "q_scale": "scale Q/G",
    "q_corr_expected": "corr(Q, Ḡ)",
    "q_scale_expected": "scale Q/Ḡ",
    "return_ceiling": "ceiling",
    "free_corr_q": "corr(Q, free)",
    "free_corr_expected": "corr(Ḡ, free)",
    "advantage_pairs": "pairs",
    "advantage_corr": "corr(ΔQ, ΔḠ)",
    "advantage_ceiling": "ΔḠ ceiling",
    "advantage_sign": "same sign",
}
CRITIC_BRANCHED = ["q_corr_expected", "q_scale_expected", "return_ceiling", "free_corr_q", "free_corr_expected"]
CRITIC_ADVANTAGE = ["advantage_pairs", "advantage_corr", "advantage_ceiling", "advantage_sign"]


def has_branched(records: list[dict[str, Any]], keys: list[str] = CRITIC_BRANCHED) -> bool:
    """Whether every record holds the critic's figures ``keys`` of the branched rollouts (:data:`CRITIC_BRANCHED`, or
    :data:`CRITIC_ADVANTAGE`: each set came with a later version of :mod:`.diagnose`)."""
    return all(k in r for r in records for k in keys)


#: Planners run at the experiments' budget (rollouts per re-plan are what makes them slow).
PLANNERS = ("GeneticAlgorithm", "ParticleSwarm", "SymbioticOrganismsSearch")


def seed_mean(records: list[dict[str, Any]], name: str) -> tuple[float, int]:
    """Mean of figure ``name`` over the seeds where it is defined, and their number: a seed whose sampled decisions
    never differ has no corr(ΔQ, ΔḠ) (NaN), which must not make the mean NaN nor count as a value."""
    values = np.array([r[name] for r in records], dtype=float)
    defined = values[~np.isnan(values)]
    return (float(defined.mean()) if defined.size else float("nan")), int(defined.size)


def _seed_mean_cell(records: list[dict[str, Any]], name: str, digits: int = 2) -> str:
    """:func:`seed_mean` formatted, with the number of seeds it is over when some seeds lack the figure ("—" when none
    has it)."""
    mean, defined = seed_mean(records, name)
    if not defined:
        return "—"
    return f"{mean:.{digits}f}" + (f" ({defined} of {len(records)} seeds)" if defined < len(records) else "")


#: Held-out reset seeds reserved for each training seed: 10,000 + 100·seed + k for k below this.
EPISODES_PER_SEED = 100


def eval_seeds(seed: int, episodes: int) -> list[int]:
    """Reset seeds of the held-out evaluation episodes of training seed ``seed`` (disjoint from training seeds)."""
    return [10_000 + EPISODES_PER_SEED * seed + k for k in range(episodes)]


def validation_seeds(seed: int, episodes: int) -> list[int]:
    """Reset seeds of the validation episodes of training seed ``seed``, which pick the best checkpoint
    (``LearnRun(validation_episodes)``): disjoint from the training seeds and from every held-out evaluation episode."""
    return [30_000 + 100 * seed + k for k in range(episodes)]


def episode_returns(agent: Any, env_id: str, seeds: list[int], planner: Callable[[gym.Env], Any] | None = None) -> list[float]:
    """Deterministic return of ``agent`` (anything with SB3's ``predict``) on one episode per reset seed.

    :param planner: builds the agent from the episode's env instead (the planners act in the env they clone)
    """
    returns = []
    for s in seeds:
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


def _reevaluation_labels(shift: str | None, decoder: str, config: dict[str, Any], more_episodes: int) -> tuple[str, str, str]:
    """The file-name suffix, the title's words and the command-line flags of a :meth:`LearnRun.reevaluate`, from its
    parts in one order: the shift, the decoding strategy unless it is the argmax, the further episodes."""
    parts: list[tuple[str, str]] = []  # (file-name part, flag) of each part that is on
    if shift:
        parts.append((f"zero_shot_{shift}", f"zero-shot {shift}"))
    if decoder != "argmax":
        settings = "".join(f"_{k}_{v}" for k, v in sorted(config.items()))
        flag = f"decoder {decoder}" + (f" --decoder-kwargs '{json.dumps(config)}'" if config else "")
        parts.append((f"decoder_{decoder}{settings}", flag))
    if more_episodes:
        parts.append((f"more_episodes_{more_episodes}", f"more-episodes {more_episodes}"))
    first = "held-out episodes"
    if shift:
        first = "zero-shot"
    elif more_episodes:
        first = f"{more_episodes} further held-out episodes per seed"
    words = [first] if decoder == "argmax" else [first, f"decoded by {decoder} {config or ''}".rstrip()]
    return "".join(f"_{part}" for part, _ in parts), ", ".join(words), "".join(f" --{flag}" for _, flag in parts)


def _one_thread(parent: int) -> None:
    """Worker set-up of ``LearnRun.run(jobs > 1)``: one torch thread per process, the TaskAlloc ids registered, and a
    watch that ends the worker when the process that started it is gone (:func:`_exit_with_parent`).

    :param parent: the pid of the process that started the pool (``os.getpid()`` there). A worker reads its own parent
        only after its interpreter has started and imported torch, seconds later; a parent killed in between would
        leave it re-parented already, watching the wrong process
    """
    import threading

    import torch as th

    import envs  # noqa: F401

    th.set_num_threads(1)
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()


def _exit_with_parent(parent: int, poll: float = 1.0) -> None:
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
        self._evaluate()

    def _on_step(self) -> bool:
        # With n_envs envs the step count grows by n_envs per call: evaluate on passing each multiple of `every`.
        if self.num_timesteps // self.every > (self.num_timesteps - self.training_env.num_envs) // self.every:
            self._evaluate()
        return True


@dataclass
class LearnRun:
    """One env's learning experiment.

    :param env: ``"RBF"``, ``"MT"``, ``"EPT"`` or ``"Almighty"``
    :param seeds: number of training seeds, ``first_seed`` .. ``first_seed + seeds − 1``
    :param steps: training env steps per seed
    :param eval_episodes: held-out evaluation episodes per seed
    :param eval_every: env steps between the curve's evaluations
    :param algo_kwargs: TwoStageSAC keywords over the env's block of ``zoo_configs/two_stage_sac.yml``
    :param planners: planner class names to run (the best is reported); empty: none
    :param milp_time_limit: seconds per MILP solve
    :param out: results folder
    :param validation_episodes: when > 0, the curve is measured on this many validation episodes per seed
        (:func:`validation_seeds`, disjoint from the held-out ones) and the checkpoint of its best point after step 0
        is evaluated on the held-out episodes too (column "best on validation"); 0: the curve uses the first two
        held-out episodes and only the final model is evaluated
    :param select_dagger: when > 0, after ``steps`` of TwoStageSAC the pointer is taught the exact cover of its
        candidates by this many DAgger iterations (:meth:`~sb3_taskalloc.TwoStageSAC.distill_select`, 10 training
        episodes each, reset seeds :func:`dagger_seed` on), and the model before it is evaluated too (column "before
        DAgger"); the curve goes on through DAgger, and a better point on the validation episodes replaces the best
        checkpoint. None: the iterations of the env block's ``SelectDAggerCallback`` (:func:`.budgets.zoo_dagger`), 0
        without one; the block's other DAgger keywords (episodes, epochs, step size, batch) apply either way
    :param dagger_imitation: DAgger's loss, ``"sequence"`` or ``"set"`` (``imitation`` of ``distill_select``); None: the
        block's, ``"sequence"`` without one
    :param first_seed: the first training seed; a replicate of a run on seeds it has not seen starts past its last seed
        (every seed's held-out, validation and DAgger episodes are derived from it, so they are new episodes too)
    :param device: where the training runs, ``"cpu"`` or ``"cuda"``. The trained model is evaluated and diagnosed on
        the CPU either way (one observation at a time is faster there). CUDA's random streams differ from the CPU's, so a
        CUDA run is a run of its own (its seed files have their own digest)
    """

    env: str
    seeds: int = 5
    steps: int = 20_000
    eval_episodes: int = 10
    eval_every: int = 2_000
    algo_kwargs: dict[str, Any] = field(default_factory=dict)
    planners: tuple[str, ...] = PLANNERS
    milp_time_limit: float = 2.0
    out: str | Path = "results/learn"
    validation_episodes: int = 0
    select_dagger: int | None = None
    dagger_imitation: str | None = None
    first_seed: int = 0
    device: str = "cpu"

    def __post_init__(self) -> None:
        check_counts({"seeds": self.seeds})
        check_counts({"first_seed": self.first_seed}, minimum=0)
        if self.device not in ("cpu", "cuda"):
            raise ValueError(f"device must be 'cpu' or 'cuda', got {self.device!r}")
        zoo = zoo_dagger(self.env_id)
        self.zoo_has_dagger = bool(zoo)
        iterations, imitation = zoo.pop("iterations", 0), zoo.pop("imitation", "sequence")
        self.select_dagger = iterations if self.select_dagger is None else self.select_dagger
        self.dagger_imitation = imitation if self.dagger_imitation is None else self.dagger_imitation
        defaults = SelectDAggerCallback().kwargs
        #: The block's DAgger keywords other than the iterations and the loss, where they differ from the defaults.
        self.dagger_kwargs: dict[str, Any] = {k: v for k, v in zoo.items() if v != defaults[k]}

    @property
    def iterations(self) -> int:
        """DAgger iterations after the steps (``select_dagger`` resolved)."""
        assert self.select_dagger is not None
        return self.select_dagger

    @property
    def imitation(self) -> str:
        """DAgger's loss (``dagger_imitation`` resolved)."""
        assert self.dagger_imitation is not None
        return self.dagger_imitation

    @property
    def seed_range(self) -> range:
        """The training seeds."""
        return range(self.first_seed, self.first_seed + self.seeds)

    @property
    def env_id(self) -> str:
        return f"TaskAlloc/{self.env}-v0"

    @property
    def hyperparameters(self) -> dict[str, Any]:
        return over_zoo(self.env_id, self.algo_kwargs)

    @property
    def key(self) -> str:
        """Digest of every setting that changes a seed's result."""
        settings: tuple[Any, ...] = (self.steps, self.eval_episodes, self.eval_every, self.planners, self.milp_time_limit)
        if self.validation_episodes:  # appended only when set: the digests of runs without it stay valid
            settings += (self.validation_episodes,)
        if self.select_dagger:
            settings += (("select_dagger", self.select_dagger),)
            if self.dagger_imitation != "sequence":  # appended only when set: the digests of earlier DAgger runs stay valid
                settings += (("dagger_imitation", self.dagger_imitation),)
            if self.dagger_kwargs:
                settings += (("dagger_kwargs", self.dagger_kwargs),)
        if self.device != "cpu":  # appended only when set: the digests of CPU runs stay valid
            settings += (("device", self.device),)
        return config_key(env_settings(self.env_id), self.hyperparameters, settings)

    def seed_path(self, seed: int) -> Path:
        return Path(self.out) / self.env / f"seed_{seed}_{self.key}.json"

    def run_seed(self, seed: int) -> dict[str, Any]:
        """Train and evaluate one seed (or read it back when it was finished before)."""
        path = self.seed_path(seed)
        if path.exists():
            return self._complete(json.loads(path.read_text()), path)
        from sb3_taskalloc.experiments.diagnose import stage_returns

        seeds = eval_seeds(seed, self.eval_episodes)
        found = self._finished_without_dagger(seed)
        model, record, curve = found if found is not None else self._train(seed, seeds)
        if curve.best is not None:  # the checkpoint the validation episodes pick, on the held-out episodes
            self._evaluate_best(model, curve, record, path)
        if self.select_dagger:
            self._dagger(model, seed, record, curve, path)
        record["curve"] = curve.points
        record["trained"] = episode_returns(model, self.env_id, seeds)
        record.update(stage_returns(model, self.env_id, seeds))  # which stage's learning the trained return owes to
        record.update(self._diagnose(model, seed))
        record.update(self.baselines(seed))
        model.save(path.with_suffix(".zip"))
        atomic_write_text(path, json.dumps(record) + "\n")
        return record

    def _curve(self, seed: int) -> Curve:
        if self.validation_episodes:
            return Curve(self.env_id, validation_seeds(seed, self.validation_episodes), self.eval_every, keep_best=True)
        return Curve(self.env_id, eval_seeds(seed, 2), self.eval_every)

    def _train(self, seed: int, seeds: list[int]) -> tuple[Any, dict[str, Any], Curve]:
        """TwoStageSAC's ``steps`` on seed ``seed``. :return: the final model, its record so far (the untrained return
        and the training time) and the curve"""
        from sb3_taskalloc import TwoStageSAC

        env, hyperparameters = training_env(self.env_id, self.hyperparameters, seed)
        model = TwoStageSAC("TAMPolicy", env, seed=seed, device=self.device, **hyperparameters)
        record: dict[str, Any] = {"seed": seed, "eval_seeds": seeds, "untrained": episode_returns(model, self.env_id, seeds)}
        curve = self._curve(seed)
        t0 = time.perf_counter()
        model.learn(self.steps, callback=curve)
        record["train_seconds"] = time.perf_counter() - t0  # the curve's evaluations included
        record["curve_seconds"] = curve.seconds
        if self.device != "cpu":  # the evaluations decide one observation at a time, which is faster on the CPU
            buffer = io.BytesIO()
            model.save(buffer)
            buffer.seek(0)
            model = TwoStageSAC.load(buffer, env=model.get_env(), device="cpu")
            record["device"] = self.device
        return model, record, curve

    def _evaluate_best(self, model: Any, curve: Curve, record: dict[str, Any], path: Path) -> None:
        """The curve's best checkpoint on the held-out episodes (``best``, ``best_step``), saved as
        ``<seed file>_best.zip``; the model keeps its own weights."""
        final = copy.deepcopy(model.policy.state_dict())
        model.policy.load_state_dict(curve.best)
        record.update(best=episode_returns(model, self.env_id, record["eval_seeds"]), best_step=curve.best_step)
        model.save(path.with_name(path.stem + "_best.zip"))
        model.policy.load_state_dict(final)
        curve.best = None  # evaluated: a later best replaces it

    def _dagger(self, model: Any, seed: int, record: dict[str, Any], curve: Curve, path: Path) -> None:
        """``select_dagger`` iterations of :meth:`~sb3_taskalloc.TwoStageSAC.distill_select`, the curve measured after
        each at the env steps of its rollouts (after the training steps); a better point on the validation episodes
        replaces the best checkpoint."""
        record["before_dagger"] = episode_returns(model, self.env_id, record["eval_seeds"])
        steps = [self.steps]

        def point(stats: dict[str, float]) -> None:
            steps[0] += int(stats["steps"])
            curve.evaluate_at(steps[0])

        t0, curve_t0 = time.perf_counter(), curve.seconds
        record["dagger"] = model.distill_select(
            self.env_id,
            iterations=self.iterations,
            imitation=self.imitation,
            seed=dagger_seed(seed),
            callback=point,
            **self.dagger_kwargs,
        )
        record["dagger_seconds"] = time.perf_counter() - t0  # the curve's evaluations included
        record["train_seconds"] += record["dagger_seconds"]
        if "curve_seconds" in record:  # absent where the training before DAgger ran before the curve was timed
            record["curve_seconds"] += curve.seconds - curve_t0
        if curve.best is not None:
            self._evaluate_best(model, curve, record, path)

    def _finished_without_dagger(self, seed: int) -> tuple[Any, dict[str, Any], Curve] | None:
        """With ``select_dagger``, the same seed of the same run without DAgger when it finished in ``out`` with its
        model: DAgger goes on from that model instead of training the same steps again. :return: the model, the
        record of its training (untrained return, training time, validation checkpoint) and its curve, or None"""
        if not self.select_dagger:
            return None
        base = dataclasses.replace(self, select_dagger=0).seed_path(seed)
        if not (base.exists() and base.with_suffix(".zip").exists()):
            return None
        from sb3_taskalloc import TwoStageSAC

        done = json.loads(base.read_text())
        model = TwoStageSAC.load(base.with_suffix(".zip"), device="cpu")
        curve = self._curve(seed)
        curve.model, curve.points, curve.best_step = (
            model,
            [(int(t), float(v)) for t, v in done["curve"]],
            done.get("best_step", 0),
        )
        kept = ("seed", "eval_seeds", "untrained", "train_seconds", "curve_seconds", "best", "best_step")
        return model, {k: done[k] for k in kept if k in done}, curve

    def _diagnose(self, model: Any, seed: int) -> dict[str, Any]:
        """The critic's calibration and the sampled return of the trained model (:func:`.diagnose.diagnose`)."""
        from sb3_taskalloc.experiments.diagnose import diagnose

        d = diagnose(model, self.env_id, episodes=min(3, self.eval_episodes), seed=20_000 + 100 * seed)
        branched = {k: getattr(d, k) for k in [*CRITIC_BRANCHED, *CRITIC_ADVANTAGE]}
        return dict(q_corr=d.q_corr, q_scale=d.q_scale, sampled=d.sampled_return, critic_reward=d.reward_timing, **branched)

    def _complete(self, record: dict[str, Any], path: Path) -> dict[str, Any]:
        """A finished seed, with what later versions measure added from its saved model (and saved):

        - a record without ``critic_reward`` had its critic compared with returns of the env reward. That is the
          critic's own reward unless it learned the commitment reward: then the figures are measured again;
        - a record without ``actor_only`` gets the returns of :func:`.diagnose.stage_returns`;
        - a record without the figures of :data:`CRITIC_BRANCHED` or :data:`CRITIC_ADVANTAGE` gets them, the critic
          against the expected return (the same seeded diagnosis, so its other critic figures come out as they were).

        Where the model is gone the record stays as it is (with a warning when its critic figures are wrong).
        """
        stale = "critic_reward" not in record and self.hyperparameters.get("reward_timing", "completion") == "commitment"
        if "critic_reward" not in record and not stale:
            record = {**record, "critic_reward": "completion"}
        branched = has_branched([record]) and has_branched([record], CRITIC_ADVANTAGE)
        if not stale and "actor_only" in record and branched:
            return record
        zip_path = path.with_suffix(".zip")
        if not zip_path.exists():
            if stale:
                warnings.warn(f"{path}: critic figures measured against the env reward, {zip_path.name} is gone", stacklevel=2)
            return record
        from sb3_taskalloc import TwoStageSAC
        from sb3_taskalloc.experiments.diagnose import stage_returns

        model = TwoStageSAC.load(zip_path, device="cpu")
        if stale or not branched:
            record = {**record, **self._diagnose(model, record["seed"])}
        if "actor_only" not in record:
            record = {**record, **stage_returns(model, self.env_id, record["eval_seeds"])}
        atomic_write_text(path, json.dumps(record) + "\n")
        return record

    def baselines(self, seed: int) -> dict[str, list[float]]:
        """Greedy, the per-step MILP and the planners on seed ``seed``'s evaluation episodes. They depend on the env,
        the episodes and their own budgets only, so they are filed under a digest of those and shared by every run of
        the algorithm's settings (each is computed once)."""
        from sb3_taskalloc import baselines as b

        seeds = eval_seeds(seed, self.eval_episodes)
        key = config_key(env_settings(self.env_id), seeds, self.milp_time_limit, PLANNER_BUDGET)
        path = Path(self.out) / self.env / f"baselines_seed_{seed}_{key}.json"
        done: dict[str, list[float]] = json.loads(path.read_text()) if path.exists() else {}
        agents: dict[str, Callable[[], list[float]]] = {
            "Greedy": lambda: episode_returns(b.GreedyAllocator(), self.env_id, seeds),
            "MILP": lambda: episode_returns(b.MILPAllocator(time_limit=self.milp_time_limit), self.env_id, seeds),
        }
        for name in self.planners:
            cls = getattr(b, name)

            def planner(env: gym.Env, cls: Any = cls) -> Any:
                return cls(env, seed=seed, **PLANNER_BUDGET)

            agents[name] = lambda planner=planner: episode_returns(None, self.env_id, seeds, planner)  # type: ignore[misc]
        for name, run in agents.items():
            if name not in done:
                done[name] = run()
                atomic_write_text(path, json.dumps(done) + "\n")
        return {name: done[name] for name in agents}

    def run(self, progress: bool = True, jobs: int = 1) -> Path:
        """Every seed (resuming), then the summary; :return: the Markdown path.

        :param jobs: seeds run at once, each in its own process with one torch thread (each seed is saved as it
            finishes, so an interrupted run keeps the finished ones)
        """
        from contextlib import ExitStack

        from tqdm.auto import tqdm

        with ExitStack() as stack:
            results: Iterable[dict[str, Any]] = map(self.run_seed, self.seed_range)
            if jobs > 1:
                import multiprocessing
                from concurrent.futures import ProcessPoolExecutor

                context = multiprocessing.get_context("spawn")  # fresh interpreters: no forked torch thread pools
                pool = stack.enter_context(
                    ProcessPoolExecutor(jobs, mp_context=context, initializer=_one_thread, initargs=(os.getpid(),))
                )
                results = pool.map(self.run_seed, self.seed_range)
            records = list(tqdm(results, total=self.seeds, desc=f"{self.env} learning", disable=not progress))
        return self.write(records)

    def write(self, records: list[dict[str, Any]]) -> Path:
        """``<out>/<env>.json`` (per seed), ``.png`` (curves) and ``.md`` (per seed, mean ± std, targets)."""
        from sb3_taskalloc.experiments.plots import plot_learning_progress

        selected = ["best"] if all("best" in r for r in records) else []
        stages = ["actor_only", "pointer_only"] if all("actor_only" in r for r in records) else []
        dagger = ["before_dagger"] if all("before_dagger" in r for r in records) else []
        columns = ["untrained", "trained", *dagger, *stages, *selected, "Greedy", "MILP", *self.planners]
        means = {c: [float(np.mean(r[c])) for r in records] for c in columns}
        best_planner = max(self.planners, key=lambda p: float(np.mean(means[p]))) if self.planners else None
        stem = Path(self.out) / self.env
        atomic_write_text(stem.with_suffix(".json"), json.dumps({"settings": self.describe(), "seeds": records}) + "\n")
        png = plot_learning_progress(
            {r["seed"]: r["curve"] for r in records},
            {"Greedy": float(np.mean(means["Greedy"])), "MILP": float(np.mean(means["MILP"]))},
            stem.with_suffix(".png"),
            f"{self.env_id}: deterministic return on {'validation' if self.validation_episodes else 'held-out'} episodes "
            "while training",
            marks={f"DAgger ({self.select_dagger} iterations) from here": self.steps} if dagger else None,
        )
        shown = ["untrained", "trained", *dagger, *stages, *selected, "Greedy", "MILP"]
        shown += [best_planner] if best_planner else []
        names = {"best": "best on validation", "actor_only": "only actor learned", "pointer_only": "only pointer learned",
                 "before_dagger": "before DAgger"}  # fmt: skip
        headers = [names.get(c, c) for c in shown]
        critic = ["q_corr", "q_scale", *(CRITIC_BRANCHED if has_branched(records) else [])]
        critic += CRITIC_ADVANTAGE if has_branched(records, CRITIC_ADVANTAGE) else []
        critic_headers = [CRITIC_COLUMNS[c] for c in critic]
        lines = [
            f"# {self.env_id}: TwoStageSAC trained {self.steps:,} steps, {len(records)} seeds"
            + (f" ({self.seed_range[0]}–{self.seed_range[-1]})" if self.first_seed else "")
            + f" × {self.eval_episodes} held-out episodes"
            + (" (trained on CUDA)" if self.device == "cuda" else ""),
            "",
            f"Command: `{self.command()}`. Curve: `{png.name}`.",
            "",
            *(
                [
                    "Trained: the final model. Best: the checkpoint with the best return on the validation episodes (the "
                    "curve), evaluated on the held-out ones.",
                    "",
                ]
                if selected
                else []
            ),
            *(
                [
                    f"Trained: {self.steps:,} steps of TwoStageSAC, then {self.select_dagger} DAgger iterations teaching "
                    "the pointer the exact cover of its candidates (`TwoStageSAC.distill_select`); before DAgger: the "
                    "model after the steps alone.",
                    "",
                ]
                if dagger
                else []
            ),
            *(
                [
                    "Only actor / pointer learned: the final model with the other stage back at its initial rule (which "
                    "stage's learning the trained return owes to).",
                    "",
                ]
                if stages
                else []
            ),
            "| seed | " + " | ".join(headers) + " | " + " | ".join(critic_headers) + " | training s |",
            "|---" * (len(shown) + len(critic) + 2) + "|",
        ]
        for k, r in enumerate(records):
            cells = " | ".join(f"{means[c][k]:.1f}" for c in shown)
            figures = " | ".join(f"{r[c]:.0f}" if c == "advantage_pairs" else f"{r[c]:.2f}" for c in critic)
            lines.append(f"| {r['seed']} | {cells} | {figures} | {r['train_seconds']:.0f} |")
        summary = " | ".join(f"{np.mean(means[c]):.1f} ± {np.std(means[c]):.1f}" for c in shown)
        critic_means = " | ".join(_seed_mean_cell(records, c, 1 if c == "advantage_pairs" else 2) for c in critic)
        lines.append(f"| mean ± std | {summary} | {critic_means} | |")
        lines += ["", *self.targets(means, records)]
        return atomic_write_text(stem.with_suffix(".md"), "\n".join(lines) + "\n")

    def targets(self, means: dict[str, list[float]], records: list[dict[str, Any]]) -> list[str]:
        """The learning targets, each with its measured value."""
        trained, init, greedy, milp = (np.array(means[c]) for c in ("trained", "untrained", "Greedy", "MILP"))
        n = len(trained)
        ratio = trained.mean() / init.mean() if init.mean() > 0 else float("nan")
        corr = np.array([r["q_corr"] for r in records])
        scale = np.array([r["q_scale"] for r in records])
        timings = " / ".join(sorted({r.get("critic_reward", "completion") for r in records}))
        milp_target = " (target ≥ 0.99)" if self.env == "EPT" else " (goal ≥ 1)"
        paired = {c: seed_mean(records, c) for c in CRITIC_ADVANTAGE} if has_branched(records, CRITIC_ADVANTAGE) else {}
        lines = [
            f"- trained / untrained (means): {ratio:.3f} (target ≥ 1.10)",
            f"- trained > untrained: {int((trained > init).sum())} of {n} seeds (target ≥ 4 of 5)",
            f"- trained > Greedy: {int((trained > greedy).sum())} of {n} seeds (target all)",
            f"- trained / per-step MILP (means): {trained.mean() / milp.mean():.3f}{milp_target}",
            f"- critic: corr(Q, G) {corr.mean():.2f} (target ≥ 0.7), scale Q/G {scale.mean():.2f} (target 0.7–1.3); G is the "
            f"discounted return of the reward the critic learns (credited at {timings})",
            *(
                [
                    f"- critic against the expected return Ḡ (the mean of branched rollouts): corr(Q, Ḡ) "
                    f"{np.mean([r['q_corr_expected'] for r in records]):.2f}, scale Q/Ḡ "
                    f"{np.mean([r['q_scale_expected'] for r in records]):.2f}; a perfect critic would reach corr(Q, G) "
                    f"{np.mean([r['return_ceiling'] for r in records]):.2f} (the noise of one rollout)",
                ]
                if has_branched(records)
                else []
            ),
            *(
                [
                    f"- the critic between two sampled decisions of a state (what the actor follows; "
                    f"{sum(r['advantage_pairs'] for r in records)} pairs where they differ): corr(ΔQ, ΔḠ) "
                    f"{paired['advantage_corr'][0]:.2f} against a ceiling of {paired['advantage_ceiling'][0]:.2f} (the "
                    f"noise of the paired branches); ΔQ has the sign of ΔḠ in {100 * paired['advantage_sign'][0]:.0f} % of "
                    "the pairs"
                    + (
                        f" (means over the {paired['advantage_corr'][1]} of {n} seeds with such pairs)"
                        if paired["advantage_corr"][1] < n
                        else ""
                    ),
                ]
                if paired
                else []
            ),
            f"- std over seeds of the trained return: {trained.std():.1f} (a smaller difference is not a result)",
        ]
        if all("curve_seconds" in r for r in records):  # what a training without the experiment's curve takes
            total = np.array([r["train_seconds"] for r in records])
            curve = np.array([r["curve_seconds"] for r in records])
            bare = total - curve
            lines += [
                f"- training time per seed: {total.min():.0f}–{total.max():.0f} s, of which the curve's evaluations "
                f"{curve.min():.0f}–{curve.max():.0f} s: {bare.min():.0f}–{bare.max():.0f} s without them",
            ]
        if "best" in means:  # the same targets for the checkpoint the validation episodes pick
            best = np.array(means["best"])
            lines += [
                f"- best on validation / untrained (means): {best.mean() / init.mean():.3f}, above untrained in "
                f"{int((best > init).sum())} of {n} seeds, above Greedy in {int((best > greedy).sum())} of {n}, "
                f"{best.mean() / milp.mean():.3f} × per-step MILP; std over seeds {best.std():.1f}",
            ]
        return lines

    def zero_shot(self, shift: str) -> Path:
        """Each finished seed's trained model on another env without training (``shift``, e.g. ``"RBF-EntityShift"``),
        against the same policy untrained and Greedy on that env's held-out episodes of the seed; writes
        ``<out>/<env>_zero_shot_<shift>.md`` and ``.json``. :return: the Markdown path."""
        return self.reevaluate(shift)

    def reevaluate(
        self,
        shift: str | None = None,
        decoder: str = "argmax",
        decoder_kwargs: dict[str, Any] | None = None,
        more_episodes: int = 0,
    ) -> Path:
        """Each finished seed's trained model and the same policy untrained, on the seed's held-out episodes of another
        env (``shift``, zero-shot) or of the training env, both decoded by the strategy ``decoder`` with
        ``decoder_kwargs`` (:mod:`~sb3_taskalloc.two_stage_sac.decoding`), against Greedy (and the per-step MILP on the
        training env); writes ``<out>/<env>[_zero_shot_<shift>][_decoder_<name>...]``, ``.md`` and ``.json``. Training
        is untouched: its sampled decisions never search. Each seed's row is saved as it finishes, under a digest of its
        model file and of the model's decisions on a few fixed states (:func:`decision_digest`), so an interrupted
        re-evaluation resumes at the seed it stopped in and a change of code that moves those decisions evaluates again.

        :param more_episodes: instead, the plain argmax on this many further held-out episodes per seed of the training
            env (the reset seeds that follow the run's own, :func:`eval_seeds`), against Greedy only; the report also
            counts the seeds above Greedy over all the run's and the further episodes, whose seed means carry a smaller
            standard error than the run's own (``<out>/<env>_more_episodes_<N>``)
        :return: the Markdown path."""
        from sb3_taskalloc import TwoStageSAC
        from sb3_taskalloc import baselines as b
        from sb3_taskalloc.two_stage_sac.decoding import get_decoding_strategy

        env_id = f"TaskAlloc/{shift}-v0" if shift else self.env_id
        config = dict(decoder_kwargs or {})
        strategy = get_decoding_strategy(decoder, **config)  # a bad name or setting fails before any evaluation
        self.check_more_episodes(more_episodes)
        if more_episodes and (shift or decoder != "argmax"):
            raise ValueError("more_episodes evaluates the plain argmax on the training env: no shift and no decoder")
        suffix, how, flags = _reevaluation_labels(shift, decoder, config, more_episodes)
        stem = Path(self.out) / (self.env + suffix)
        rows: list[dict[str, Any]] = []
        for seed in self.seed_range:
            path = self.seed_path(seed).with_suffix(".zip")
            if not path.exists():
                raise FileNotFoundError(f"seed {seed} has no trained model at {path}: run the experiment first")
            model_digest = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
            trained = TwoStageSAC.load(path, env=gym.make(env_id), device="cpu")
            trained.set_decoder(decoder, **config)
            decisions = decision_digest(trained, env_id)
            done = self.seed_path(seed).with_name(f"{stem.name}_seed_{seed}_{self.key}.json")
            saved = json.loads(done.read_text()) if done.exists() else {}
            if saved.get("model_digest") == model_digest and saved.get("decisions") == decisions:
                rows.append(saved)
                continue
            seeds = eval_seeds(seed, self.eval_episodes + more_episodes)[self.eval_episodes if more_episodes else 0 :]
            untrained = TwoStageSAC("TAMPolicy", env_id, seed=seed, device="cpu", policy_kwargs=trained.policy_kwargs)
            untrained.set_decoder(get_decoding_strategy(decoder, **config))
            row = {"seed": seed, "trained": episode_returns(trained, env_id, seeds),
                   "untrained": episode_returns(untrained, env_id, seeds)}  # fmt: skip
            if shift or more_episodes:  # the per-step MILP takes seconds per step: the training env's held-out episodes only
                row["Greedy"] = episode_returns(b.GreedyAllocator(), env_id, seeds)
            else:
                row.update(self.baselines(seed))
            row["model_digest"], row["decisions"] = model_digest, decisions
            atomic_write_text(done, json.dumps(row) + "\n")
            rows.append(row)
        settings = {"settings": self.describe(), "env": env_id, "decoder": repr(strategy), "seeds": rows}
        atomic_write_text(stem.with_suffix(".json"), json.dumps(settings))
        columns = ["untrained", "trained", "Greedy", *([] if shift or more_episodes else ["MILP"])]
        means = {c: np.array([np.mean(r[c]) for r in rows]) for c in columns}
        lines = [
            f"# {env_id}: {how}, the models of `{self.env}.md` ({self.steps:,} steps on {self.env_id})",
            "",
            f"Command: `{self.command()}{flags}`",
            "",
            "| seed | " + " | ".join(columns) + " |",
            "|---" * (len(columns) + 1) + "|",
            *(f"| {r['seed']} | " + " | ".join(f"{means[c][k]:.1f}" for c in columns) + " |" for k, r in enumerate(rows)),
            "| mean ± std | " + " | ".join(f"{means[c].mean():.1f} ± {means[c].std():.1f}" for c in columns) + " |",
            "",
            f"- trained ≥ Greedy: {int((means['trained'] >= means['Greedy']).sum())} of {len(rows)} seeds (target all)",
            f"- trained > untrained: {int((means['trained'] > means['untrained']).sum())} of {len(rows)} seeds, "
            f"{means['trained'].mean() / means['untrained'].mean():.3f} × (means)",
            *(
                []
                if shift or more_episodes
                else [f"- trained / per-step MILP (means): {means['trained'].mean() / means['MILP'].mean():.3f}"]
            ),
            *(self._over_all_episodes(rows) if more_episodes else []),
        ]
        return atomic_write_text(stem.with_suffix(".md"), "\n".join(lines) + "\n")

    def check_more_episodes(self, more_episodes: int) -> None:
        """A clear error where :meth:`reevaluate`'s ``more_episodes`` is neither 0 (off) nor a positive integer, or would
        reach into the next training seed's held-out reset seeds (each seed has :data:`EPISODES_PER_SEED`)."""
        if more_episodes:
            check_counts({"more_episodes": more_episodes})
        if self.eval_episodes + more_episodes > EPISODES_PER_SEED:
            raise ValueError(
                f"eval_episodes + more_episodes must be at most {EPISODES_PER_SEED} (each seed's share of the held-out "
                f"reset seeds), got {self.eval_episodes} + {more_episodes}"
            )

    def _over_all_episodes(self, rows: list[dict[str, Any]]) -> list[str]:
        """The report's lines of :meth:`reevaluate`'s ``more_episodes``: each seed over the run's own held-out episodes
        and the further ones together, with the standard error of its mean lead over Greedy (paired by episode)."""
        header = "| seed | episodes | untrained | trained | Greedy | trained − Greedy ± s.e. |"
        lines = ["", "Over the run's own and the further held-out episodes together:", "", header, "|---" * 6 + "|"]
        leads, gains = [], []
        for row in rows:
            own = json.loads(self.seed_path(row["seed"]).read_text())
            both = {c: np.array(own[c] + row[c]) for c in ("untrained", "trained", "Greedy")}
            lead = both["trained"] - both["Greedy"]
            leads.append(lead.mean())
            gains.append(both["trained"].mean() - both["untrained"].mean())
            lines.append(
                f"| {row['seed']} | {lead.size} | {both['untrained'].mean():.1f} | {both['trained'].mean():.1f} | "
                f"{both['Greedy'].mean():.1f} | {lead.mean():+.1f} ± {lead.std(ddof=1) / np.sqrt(lead.size):.1f} |"
            )
        leads_, gains_ = np.array(leads), np.array(gains)
        return [
            *lines,
            "",
            f"- trained ≥ Greedy: {int((leads_ >= 0).sum())} of {len(rows)} seeds over all episodes; lead {leads_.mean():+.1f}"
            f" ± {leads_.std():.1f} per seed",
            f"- trained > untrained: {int((gains_ > 0).sum())} of {len(rows)} seeds over all episodes",
        ]

    def describe(self) -> dict[str, Any]:
        return {
            "env": self.env_id,
            "steps": self.steps,
            "eval_episodes": self.eval_episodes,
            "hyperparameters": self.hyperparameters,
            "planners": list(self.planners),
            "validation_episodes": self.validation_episodes,
            "select_dagger": self.select_dagger,
            "dagger_imitation": self.dagger_imitation,
            **({"dagger_kwargs": self.dagger_kwargs} if self.dagger_kwargs else {}),
            "first_seed": self.first_seed,
            "device": self.device,
            "key": self.key,
        }

    def command(self) -> str:
        extra = f" --algo-kwargs '{json.dumps(self.algo_kwargs)}'" if self.algo_kwargs else ""
        planners = " --planners " + (" ".join(self.planners) if self.planners else "none")
        if self.validation_episodes:
            planners += f" --validation-episodes {self.validation_episodes}"
        if self.select_dagger or self.zoo_has_dagger:  # 0 is written out when it turns the zoo block's DAgger off
            planners += f" --select-dagger {self.select_dagger}"
        if self.select_dagger and (self.dagger_imitation != "sequence" or self.zoo_has_dagger):
            planners += f" --dagger-imitation {self.dagger_imitation}"
        if self.first_seed:
            planners += f" --first-seed {self.first_seed}"
        if self.device != "cpu":
            planners += f" --device {self.device}"
        return (
            f"python -m sb3_taskalloc.experiments learn --env {self.env} --seeds {self.seeds} --steps {self.steps} "
            f"--eval-episodes {self.eval_episodes} --eval-every {self.eval_every}{planners}{extra}"
        )
