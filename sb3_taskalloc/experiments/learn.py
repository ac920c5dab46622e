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
import io
import json
import os
import shutil
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sb3_taskalloc.common.utils import atomic_write_text, check_counts
from sb3_taskalloc.experiments import checkpoint, evaluation, learn_report, reevaluate
from sb3_taskalloc.experiments.budgets import MILP_NODE_LIMIT, code_defaults, config_key, env_settings
from sb3_taskalloc.experiments.evaluation import PLANNERS, Curve, eval_seeds, one_thread, validation_seeds

# The DAgger rollouts of training seed ``seed`` run from 50,000 + 1000·seed, clear of the held-out (10,000 + 100·seed),
# validation (30,000 + 100·seed) and diagnosis episodes; SelectDAggerCallback rolls out the same episodes by default.
from sb3_taskalloc.two_stage_sac.callbacks import SelectDAggerCallback, dagger_seed
from sb3_taskalloc.zoo_config import over_zoo, training_env, zoo_dagger


@dataclass
class LearnRun:
    """One env's learning experiment.

    :param env: a registered env without ``TaskAlloc/`` and ``-v0``: ``"RBF"``, ``"MT"``, ``"EPT"``, ``"Almighty"`` or a
        shifted one (``"MT-EntityShift"``)
    :param seeds: number of training seeds, ``first_seed`` .. ``first_seed + seeds − 1``
    :param steps: training env steps per seed
    :param eval_episodes: held-out evaluation episodes per seed
    :param eval_every: env steps between the curve's evaluations
    :param algo_kwargs: TwoStageSAC keywords over the env's block of ``zoo_configs/two_stage_sac.yml``
    :param planners: planner class names to run (the best is reported); empty: none
    :param milp_node_limit: HiGHS nodes per solve of the per-step MILP reference (:data:`.budgets.MILP_NODE_LIMIT`)
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
    milp_node_limit: int = MILP_NODE_LIMIT
    out: str | Path = "runs/learn"
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
        #: Set by :meth:`run` with one job: each seed's training steps and DAgger iterations show progress bars.
        self.progress_bars = False

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
        settings: tuple[Any, ...] = (self.steps, self.eval_episodes, self.eval_every, self.planners, self.milp_node_limit)
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
        return config_key(env_settings(self.env_id), self.hyperparameters, (*settings, ("code", code_defaults())))

    def seed_path(self, seed: int) -> Path:
        return Path(self.out) / self.env / f"seed_{seed}_{self.key}.json"

    def training_folder(self, seed: int) -> Path:
        """The checkpoints of seed ``seed``'s training in progress (:mod:`.checkpoint`)."""
        return checkpoint.training_folder(self.seed_path(seed))

    def run_seed(self, seed: int) -> dict[str, Any]:
        """Train and evaluate one seed (or read it back when it was finished before)."""
        path = self.seed_path(seed)
        trained = path.with_name(path.stem + "_trained.json")  # the seed's training done, its evaluations not
        if path.exists():
            for left in (trained, trained.with_suffix(".zip")):  # left by a kill between the seed's save and their removal
                left.unlink(missing_ok=True)
            shutil.rmtree(self.training_folder(seed), ignore_errors=True)
            return learn_report.complete_record(self, json.loads(path.read_text()), path)
        from sb3_taskalloc.experiments.diagnose import stage_returns

        if trained.exists() and trained.with_suffix(".zip").exists():
            from sb3_taskalloc import TwoStageSAC

            model, record = TwoStageSAC.load(trained.with_suffix(".zip"), device="cpu"), json.loads(trained.read_text())
            self._say(f"seed {seed}: its training finished before")
        else:
            model, record = self._trained_model(seed, path)
            model.save(trained.with_suffix(".zip"))  # before the record, whose presence says that both are whole
            atomic_write_text(trained, json.dumps(record) + "\n")
            shutil.rmtree(self.training_folder(seed), ignore_errors=True)  # its checkpoints: the trained seed is saved
        self._say(f"seed {seed}: evaluating the trained model, its stages, the diagnosis and the baselines")
        seeds = record["eval_seeds"]
        record["trained"] = evaluation.episode_returns(model, self.env_id, seeds)
        record.update(stage_returns(model, self.env_id, seeds))  # which stage's learning the trained return owes to
        record.update(learn_report.diagnose_record(self, model, seed))
        record.update(self.baselines(seed))
        model.save(path.with_suffix(".zip"))
        atomic_write_text(path, json.dumps(record) + "\n")
        trained.unlink(missing_ok=True)
        trained.with_suffix(".zip").unlink(missing_ok=True)
        return record

    def _trained_model(self, seed: int, path: Path) -> tuple[Any, dict[str, Any]]:
        """Seed ``seed`` trained, its DAgger phase included, with its record so far (the untrained return, the curve,
        the validation checkpoint's return)."""
        found = self._finished_without_dagger(seed)
        phase = "training" if found is None else "DAgger after its finished training"
        self._say(f"seed {seed} ({seed - self.first_seed + 1} of {self.seeds}): {phase}")
        model, record, curve = found if found is not None else self._train(seed, eval_seeds(seed, self.eval_episodes))
        if curve.best is not None:  # the checkpoint the validation episodes pick, on the held-out episodes
            self._evaluate_best(model, curve, record, path)
        if self.select_dagger:
            self._dagger(model, seed, record, curve, path)
        record["curve"] = curve.points
        return model, record

    def _say(self, what: str) -> None:
        """A line on the seed's phase where the phases show progress bars (one job)."""
        if self.progress_bars:
            print(f"{self.env} learning, {what}", flush=True)

    def _curve(self, seed: int) -> Curve:
        if self.validation_episodes:
            return Curve(self.env_id, validation_seeds(seed, self.validation_episodes), self.eval_every, keep_best=True)
        return Curve(self.env_id, eval_seeds(seed, 2), self.eval_every)

    def _train(self, seed: int, seeds: list[int]) -> tuple[Any, dict[str, Any], Curve]:
        """TwoStageSAC's ``steps`` on seed ``seed``. :return: the final model, its record so far (the untrained return
        and the training time) and the curve"""
        from sb3_taskalloc import TwoStageSAC

        curve = self._curve(seed)
        folder = self.training_folder(seed)
        resumed = checkpoint.resume_training(folder, curve, self.device)
        if resumed is not None:  # a kill stopped this seed's training: it goes on from its checkpoint, exactly
            model, record, seconds = resumed
            self._say(f"seed {seed}: training resumed at step {model.num_timesteps}")
        else:
            env, hyperparameters = training_env(self.env_id, self.hyperparameters, seed)
            model = TwoStageSAC("TAMPolicy", env, seed=seed, device=self.device, **hyperparameters)
            record = {
                "seed": seed,
                "eval_seeds": seeds,
                "untrained": evaluation.episode_returns(model, self.env_id, seeds),
                "machine": evaluation.machine(),  # where a seed's figures were measured, for comparing two records
            }
            seconds = 0.0
        saving = checkpoint.TrainingCheckpoint(folder, curve, record, seconds)
        t0 = time.perf_counter()
        model.learn(
            self.steps - model.num_timesteps,
            callback=[curve, saving],
            progress_bar=self.progress_bars,
            reset_num_timesteps=resumed is None,
        )
        record["train_seconds"] = seconds + time.perf_counter() - t0  # the curve's evaluations included
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
        record.update(best=evaluation.episode_returns(model, self.env_id, record["eval_seeds"]), best_step=curve.best_step)
        model.save(path.with_name(path.stem + "_best.zip"))
        model.policy.load_state_dict(final)
        curve.best = None  # evaluated: a later best replaces it

    def _dagger(self, model: Any, seed: int, record: dict[str, Any], curve: Curve, path: Path) -> None:
        """``select_dagger`` iterations of :meth:`~sb3_taskalloc.TwoStageSAC.distill_select`, the curve measured after
        each at the env steps of its rollouts (after the training steps); a better point on the validation episodes
        replaces the best checkpoint."""
        record["before_dagger"] = evaluation.episode_returns(model, self.env_id, record["eval_seeds"])
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
            progress_bar=self.progress_bars,
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

    def baselines(self, seed: int) -> dict[str, Any]:
        """Greedy, the per-step MILP and the planners on seed ``seed``'s episodes (:func:`.evaluation.baseline_returns`)."""
        return evaluation.baseline_returns(self, seed)

    def run(self, progress: bool = True, jobs: int = 1) -> Path:
        """Every seed (resuming), then the summary; :return: the Markdown path.

        :param jobs: seeds run at once, each in its own process with one torch thread (each seed is saved as it
            finishes, so an interrupted run keeps the finished ones)
        """
        from contextlib import ExitStack

        from tqdm.auto import tqdm

        # One job: the seed in progress shows its steps and DAgger iterations; several: one bar over the seeds.
        self.progress_bars = progress and jobs == 1
        with ExitStack() as stack:
            results: Iterable[dict[str, Any]] = map(self.run_seed, self.seed_range)
            if jobs > 1:
                import multiprocessing
                from concurrent.futures import ProcessPoolExecutor

                context = multiprocessing.get_context("spawn")  # fresh interpreters: no forked torch thread pools
                pool = stack.enter_context(
                    ProcessPoolExecutor(jobs, mp_context=context, initializer=one_thread, initargs=(os.getpid(),))
                )
                results = pool.map(self.run_seed, self.seed_range)
            bar = progress and not self.progress_bars
            records = list(tqdm(results, total=self.seeds, desc=f"{self.env} learning", disable=not bar))
        return self.write(records)

    def write(self, records: list[dict[str, Any]]) -> Path:
        """``<out>/<env>.json`` (per seed), ``.png`` (curves) and ``.md`` (per seed, mean ± std, targets)."""
        return learn_report.write(self, records)

    def zero_shot(self, shift: str) -> Path:
        """Each finished seed's trained model on the env ``shift`` (e.g. ``"RBF-EntityShift"``) without training."""
        return reevaluate.reevaluate(self, shift)

    def reevaluate(
        self,
        shift: str | None = None,
        decoder: str = "argmax",
        decoder_kwargs: dict[str, Any] | None = None,
        more_episodes: int = 0,
    ) -> Path:
        """Each finished seed's trained model and the same policy untrained, zero-shot on ``shift``, decoded by
        ``decoder`` or on ``more_episodes`` further held-out episodes (:func:`.reevaluate.reevaluate`)."""
        return reevaluate.reevaluate(self, shift, decoder, decoder_kwargs, more_episodes)

    def check_more_episodes(self, more_episodes: int) -> None:
        """A clear error for a bad ``more_episodes`` of :meth:`reevaluate` (:func:`.reevaluate.check_more_episodes`)."""
        reevaluate.check_more_episodes(self, more_episodes)

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
