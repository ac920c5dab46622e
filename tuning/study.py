"""Optuna studies of TwoStageSAC that scale from one process to many machines.

``python -m tuning.study --env TaskAlloc/RBF-v0 --n-trials 50 --n-timesteps 20000 --study-name rbf``

Every process started with the same ``--study-name`` and ``--storage`` is a worker of one study: TPE sampler, median
pruner on the intermediate evaluations, until the study holds ``--n-trials`` finished (complete or pruned) trials.

Storage:

- default: an Optuna journal file ``<out>/<study-name>.log`` (file-locked, append-only: a worker killed at any
  moment loses no completed trial). Several workers on one machine, or on machines sharing the folder, run the same
  study. A worker records a heartbeat on its running trial every ``--heartbeat-interval`` seconds; a worker that starts
  later fails the running trials whose heartbeat is older than ``--heartbeat-grace`` and queues their parameters again.
  A last record cut mid-line (a crash while writing) is moved aside to ``<journal>.torn-<time>`` before anything is
  appended; a journal damaged elsewhere is refused with the line that is wrong.
- ``postgresql://user:password@host/db`` (or any SQLAlchemy URL): Optuna's RDB storage with its own heartbeats.
  Workers on many machines share the study, and may all start at once on an empty database (on PostgreSQL they create
  Optuna's tables one at a time under an advisory lock); a trial whose worker stops sending heartbeats is failed after
  the grace period and retried (``RetryHeartbeatStaleTrialCallback``).

The study records its env, env keywords, trial budget and search space; resuming it with other ones is refused (their
trials would be mixed). When a worker finishes it writes ``<study-name>/`` next to the journal file (under ``--out``
for an RDB URL): ``trials.csv`` (every trial), ``best.yml`` (the best parameters as a zoo YAML block keyed by the env
id, ready to paste into ``zoo_configs/two_stage_sac.yml``) and ``importance.png`` (parameter importances, PED-ANOVA).
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import socket
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import Any

import gymnasium as gym
import optuna
import yaml
from optuna.trial import TrialState
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import VecEnv

import envs  # noqa: F401  (registers the TaskAlloc/* ids)
from sb3_taskalloc import TwoStageSAC
from sb3_taskalloc.common.utils import atomic_path, atomic_write_text
from sb3_taskalloc.experiments.budgets import full_env_id
from sb3_taskalloc.zoo_config import merge_settings, training_env, zoo_block, zoo_hyperparameters
from tuning.samplers import TrialSeededTPESampler, convert_two_stage_sac_params, sample_two_stage_sac_params
from tuning.storage import journal_path, make_storage

#: Reset seed of the evaluation episodes (disjoint from the training seeds, which start at ``--seed``).
EVAL_SEED = 90_000

#: Trial states that count towards ``--n-trials``.
FINISHED = (TrialState.COMPLETE, TrialState.PRUNED)


class TrialEvalCallback(EvalCallback):
    """:class:`EvalCallback` that reports each evaluation to an Optuna trial and stops training when the trial is
    pruned (or when the evaluation is not a finite number).

    :param eval_env: evaluation environment
    :param trial: the trial to report to
    :param n_eval_episodes: episodes per evaluation
    :param eval_freq: evaluate every ``eval_freq`` calls (env steps with one env)
    :param deterministic: deterministic evaluation
    """

    def __init__(
        self,
        eval_env: gym.Env | VecEnv,
        trial: optuna.Trial,
        n_eval_episodes: int = 5,
        eval_freq: int = 10_000,
        deterministic: bool = True,
    ) -> None:
        super().__init__(
            eval_env, n_eval_episodes=n_eval_episodes, eval_freq=eval_freq, deterministic=deterministic, verbose=0
        )
        self.trial = trial
        self.eval_idx = 0
        self.is_pruned = False

    def _on_step(self) -> bool:
        if self.eval_freq > 0 and self.n_calls % self.eval_freq == 0:
            self.eval_env.seed(EVAL_SEED)  # every evaluation of every trial on the same episodes
            super()._on_step()
            self.eval_idx += 1
            if not math.isfinite(self.last_mean_reward):
                self.is_pruned = True
                return False
            self.trial.report(self.last_mean_reward, self.eval_idx)
            if self.trial.should_prune():
                self.is_pruned = True
                return False
        return True


def output_folder(args: argparse.Namespace) -> Path:
    """Where the summaries go: ``<study-name>/`` beside the journal file, or under ``--out`` for an RDB URL."""
    if args.storage is None or "://" not in args.storage:
        return journal_path(args.storage, args.study_name, args.out).parent / args.study_name
    return Path(args.out) / args.study_name


class Heartbeat:
    """Records the time on a running trial (user attribute ``heartbeat``) every ``interval`` seconds from a thread,
    so that other workers can tell a live trial from one whose worker died (journal storage has no heartbeat of its
    own).

    :param trial: the running trial
    :param interval: seconds between heartbeats
    """

    def __init__(self, trial: optuna.Trial, interval: float) -> None:
        self.trial, self.interval = trial, interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self.trial.set_user_attr("heartbeat", time.time())

    def __enter__(self) -> Heartbeat:
        self.trial.set_user_attr("heartbeat", time.time())
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def _fail_stale(study: optuna.Study) -> list[int]:
    """RDB storage: Optuna's own heartbeat check fails the stale trials and its callback retries them."""
    before = {t.number for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))}
    optuna.storages.fail_stale_trials(study)
    return sorted(before - {t.number for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))})


def recover_stale_trials(study: optuna.Study, grace_period: float) -> list[int]:
    """Fail the running trials whose last heartbeat is older than ``grace_period`` seconds (their worker died, on any
    host) and queue their parameters again. :return: the numbers of the trials failed."""
    now = time.time()
    failed = []
    for trial in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
        start = trial.datetime_start.timestamp() if trial.datetime_start is not None else now
        if now - float(trial.user_attrs.get("heartbeat", start)) <= grace_period:
            continue
        study.tell(trial.number, state=TrialState.FAIL)  # by number: the trial was started by another (dead) worker
        study.enqueue_trial(trial.params, user_attrs={"retry_of": trial.number})
        failed.append(trial.number)
    return failed


def search_space() -> dict[str, str]:
    """The distributions :func:`sample_two_stage_sac_params` draws from, as JSON text by parameter name."""
    probe = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    trial = probe.ask()
    sample_two_stage_sac_params(trial, 0, 1, {})
    return {name: optuna.distributions.distribution_to_json(d) for name, d in sorted(trial.distributions.items())}


def check_study_settings(study: optuna.Study, args: argparse.Namespace) -> None:
    """Record the study's env, env keywords, trial budget, evaluation settings and search space on its first run, and
    refuse to resume it with other ones: trials of another env, budget or evaluation would be compared as if alike."""
    settings = {
        "env": args.env,
        "env_kwargs": args.env_kwargs or {},
        "n_timesteps": args.n_timesteps,
        "eval_episodes": args.eval_episodes,
        "n_evaluations": args.n_evaluations,
        "search_space": search_space(),
        "zoo_block": zoo_block(args.env),  # what the trials train under the sampled settings
    }
    recorded = study.user_attrs.get("settings")  # one attribute: workers starting together never see half of it
    if recorded is None and not study.trials:
        study.set_user_attr("settings", settings)
        return
    differ = sorted(key for key in settings if (recorded or {}).get(key) != settings[key])
    if differ:
        shown = {key: (recorded or {}).get(key, "not recorded") for key in differ if key != "search_space"}
        raise ValueError(
            f"study {study.study_name!r} was run with other settings ({', '.join(differ)}; recorded: {shown}): "
            "resume it with the same --env, --env-kwargs, --n-timesteps, --eval-episodes and --n-evaluations (and the "
            "same zoo block and search space), or choose another --study-name"
        )


def objective(trial: optuna.Trial, args: argparse.Namespace) -> float:
    """Train TwoStageSAC with sampled hyperparameters and return its last evaluation (mean episode return).

    Pruned by the median pruner on intermediate evaluations, and when training diverges (NaN)."""
    trial.set_user_attr("host", socket.gethostname())  # for reading the study; liveness is the heartbeat
    trial.set_user_attr("pid", os.getpid())
    env_kwargs = args.env_kwargs or {}
    sampled = sample_two_stage_sac_params(trial, 0, 1, {})
    # A warm-up as long as the budget would train nothing: it takes at most half the budget.
    sampled["learning_starts"] = min(sampled["learning_starts"], args.n_timesteps // 2)
    trial.set_user_attr("learning_starts", sampled["learning_starts"])
    # The trial trains the env's zoo block (its n_envs, rule, held actor...) with the sampled settings over it, so the
    # best trial's block (best.yml) trains as the trial did.
    seed = args.seed + trial.number
    env, kwargs = training_env(args.env, merge_settings(zoo_hyperparameters(args.env), sampled), seed, env_kwargs)
    n_envs = env.num_envs if isinstance(env, VecEnv) else 1
    eval_env = Monitor(gym.make(args.env, **env_kwargs))
    every = max(args.n_timesteps // args.n_evaluations // n_envs, 1)  # in callback calls, each of n_envs env steps
    callback = TrialEvalCallback(eval_env, trial, n_eval_episodes=args.eval_episodes, eval_freq=every)
    model = TwoStageSAC("TAMPolicy", env, seed=seed, device=args.device, **kwargs)
    try:
        model.learn(args.n_timesteps, callback=callback)
    except (AssertionError, ValueError, RuntimeError, FloatingPointError) as error:  # divergence: a NaN loss or weight
        raise optuna.TrialPruned(f"training failed: {error}") from error
    finally:
        eval_env.close()
        model.env.close()  # type: ignore[union-attr]
    if callback.is_pruned:
        raise optuna.TrialPruned()
    if not math.isfinite(callback.last_mean_reward):
        raise optuna.TrialPruned("evaluation returned a non-finite value")
    return float(callback.last_mean_reward)


def count(study: optuna.Study, states: tuple[TrialState, ...], below: int | None = None) -> int:
    """Trials in ``states`` (with a number below ``below`` when given)."""
    return sum(below is None or t.number < below for t in study.get_trials(deepcopy=False, states=states))


def open_study(args: argparse.Namespace) -> optuna.Study:
    """Create the study, or load it by name (resume): TPE sampler, median pruner on the intermediate evaluations."""
    study = optuna.create_study(
        study_name=args.study_name,
        storage=make_storage(args.storage, args.study_name, args.out, args.heartbeat_interval, args.heartbeat_grace),
        direction="maximize",
        load_if_exists=True,
        sampler=optuna.samplers.TPESampler(n_startup_trials=args.n_startup_trials, seed=args.seed, multivariate=True),
        pruner=optuna.pruners.MedianPruner(n_startup_trials=args.n_startup_trials, n_warmup_steps=args.n_evaluations // 3),
    )
    check_study_settings(study, args)
    # Each trial samples from a state set by --seed and its trial number (unique across workers).
    study.sampler = TrialSeededTPESampler(n_startup_trials=args.n_startup_trials, seed=args.seed, multivariate=True)
    return study


def run_worker(args: argparse.Namespace) -> optuna.Study:
    """Run trials until the study holds ``args.n_trials`` finished trials; :return: the study."""
    study = open_study(args)
    journal = args.storage is None or "://" not in args.storage
    while count(study, FINISHED) < args.n_trials:
        # Live recovery: a worker that died mid-trial leaves it RUNNING; once its heartbeat is stale it is failed and
        # its parameters queued again, by whichever worker looks first, at start or between its trials.
        recovered = recover_stale_trials(study, args.heartbeat_grace) if journal else _fail_stale(study)
        if recovered:
            print(f"re-queued the trials of dead workers: {recovered}")
        if count(study, (*FINISHED, TrialState.RUNNING)) >= args.n_trials:
            time.sleep(args.heartbeat_interval)  # the other workers' trials finish, or go stale and are recovered
            continue
        trial = study.ask()
        # Another worker may have started the last trial between the check and ask(): this one would be surplus.
        if count(study, (*FINISHED, TrialState.RUNNING), below=trial.number) >= args.n_trials:
            trial.set_user_attr("surplus", True)
            study.tell(trial, state=TrialState.FAIL)
            continue  # wait for the other worker's trial (or recover it, should that worker die)
        try:
            if journal:
                with Heartbeat(trial, args.heartbeat_interval):
                    value = objective(trial, args)
            else:
                value = objective(trial, args)
        except optuna.TrialPruned as pruned:
            study.tell(trial, state=TrialState.PRUNED)
            print(f"trial {trial.number} pruned {pruned}".rstrip())
            continue
        except BaseException:  # a crash or Ctrl-C: the trial is failed and its parameters queued for a retry
            study.tell(trial, state=TrialState.FAIL)
            study.enqueue_trial(trial.params, user_attrs={"retry_of": trial.number})
            raise
        study.tell(trial, value)
        print(f"trial {trial.number}: {value:.4g} (best {study.best_value:.4g}, {count(study, FINISHED)}/{args.n_trials})")
    return study


def write_trials_csv(study: optuna.Study, path: Path) -> None:
    """One row per trial: number, state, value, start, duration (s), ``params_*`` and ``user_attrs_*`` columns."""
    trials = study.get_trials(deepcopy=False)
    params = sorted({k for t in trials for k in t.params})
    attrs = sorted({k for t in trials for k in t.user_attrs})
    with atomic_path(path) as tmp, tmp.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(
            ["number", "state", "value", "datetime_start", "duration_s"]
            + [f"params_{k}" for k in params]
            + [f"user_attrs_{k}" for k in attrs]
        )
        for t in trials:
            duration = t.duration.total_seconds() if t.duration is not None else ""
            writer.writerow(
                [t.number, t.state.name, "" if t.value is None else t.value, t.datetime_start or "", duration]
                + [t.params.get(k, "") for k in params]
                + [t.user_attrs.get(k, "") for k in attrs]
            )


def summarize(study: optuna.Study, env_id: str, folder: Path) -> dict[str, Any]:
    """Write ``trials.csv``, ``best.yml`` (zoo YAML block) and ``importance.png``; :return: the best hyperparameters."""
    folder.mkdir(parents=True, exist_ok=True)
    write_trials_csv(study, folder / "trials.csv")
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    if not complete:
        print("no completed trial yet")
        return {}
    best = convert_two_stage_sac_params(study.best_trial.params)
    best["learning_starts"] = study.best_trial.user_attrs.get("learning_starts", best.get("learning_starts"))
    # The env's zoo block with the best settings over it (the trials trained it): it replaces the block as it stands.
    budget = study.user_attrs.get("settings", {}).get("n_timesteps")
    block = {env_id: merge_settings({**zoo_block(env_id), "n_timesteps": budget}, best)}
    header = (
        f"# Best of study {study.study_name!r}: trial {study.best_trial.number}, mean return {study.best_value:.4g}; "
        f"{env_id}'s zoo block with the trial's settings over it.\n# The trials measured the training steps: the "
        "block's DAgger callback, if any, ran in none of them.\n"
    )
    atomic_write_text(folder / "best.yml", header + yaml.safe_dump(block, sort_keys=False))
    if len(complete) >= 2:
        from optuna.importance import PedAnovaImportanceEvaluator

        from sb3_taskalloc.experiments.plots import pyplot, save_figure

        pyplot()  # the headless backend before optuna's matplotlib module loads
        from optuna.visualization.matplotlib import plot_param_importances

        try:
            with warnings.catch_warnings():  # experimental-API notice; "equal importances" with very few trials
                warnings.simplefilter("ignore")
                ax = plot_param_importances(study, evaluator=PedAnovaImportanceEvaluator())
            figure = ax.get_figure(root=True)
            assert figure is not None
            save_figure(figure, folder / "importance.png", dpi=120)
        except (ValueError, RuntimeError) as error:  # too few distinct trials for an importance estimate
            print(f"no importance plot: {error}")
    print(f"best trial {study.best_trial.number}: {study.best_value:.4g}\n{header}{yaml.safe_dump(block, sort_keys=False)}")
    print(f"wrote {folder}/trials.csv, best.yml" + (", importance.png" if (folder / "importance.png").exists() else ""))
    return best


def _env_kwargs(text: str) -> dict[str, Any]:
    value = yaml.safe_load(text)
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"--env-kwargs must be a YAML/JSON mapping, got {text!r}")
    return value


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """The module docstring as written, and every option's default."""


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m tuning.study", description=__doc__, formatter_class=HelpFormatter)
    parser.add_argument("--env", type=full_env_id, default="TaskAlloc/RBF-v0", help="env id")
    parser.add_argument("--env-kwargs", type=_env_kwargs, default=None, help='env keywords as YAML, e.g. "{max_tasks: 5}"')
    parser.add_argument("--n-trials", type=int, default=50, help="finished trials of the whole study (all workers)")
    parser.add_argument("--n-timesteps", type=int, default=20_000, help="env steps per trial")
    parser.add_argument("--n-evaluations", type=int, default=4, help="intermediate evaluations per trial (pruning points)")
    parser.add_argument("--eval-episodes", type=int, default=3, help="episodes per evaluation")
    parser.add_argument("--n-startup-trials", type=int, default=5, help="random trials before TPE; trials before pruning")
    parser.add_argument("--study-name", default=None, help="study name (default: tune-<env name>)")
    parser.add_argument("--storage", default=None, help="journal file path or RDB URL (default: <out>/<study-name>.log)")
    parser.add_argument("--out", default="studies", help="folder of the default journal file; summaries of an RDB study")
    parser.add_argument("--heartbeat-interval", type=int, default=30, help="seconds between a running trial's heartbeats")
    parser.add_argument("--heartbeat-grace", type=int, default=120, help="seconds without a heartbeat: the trial is dead")
    parser.add_argument("--seed", type=int, default=0, help="trial k trains with seed + k; samplers use it with the pid")
    parser.add_argument("--device", default="auto", help="torch device")
    args = parser.parse_args(argv)
    for name in ("n_trials", "n_timesteps", "n_evaluations", "eval_episodes", "heartbeat_interval", "heartbeat_grace"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.env not in gym.registry:
        parser.error(
            f"unknown env id {args.env!r}; TaskAlloc ids: {sorted(k for k in gym.registry if k.startswith('TaskAlloc/'))}"
        )
    args.study_name = args.study_name or "tune-" + args.env.split("/")[-1]
    return args


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    import torch as th

    th.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        study = run_worker(args)
    except ValueError as error:  # a damaged journal or a study of other settings: say so, write nothing
        raise SystemExit(f"error: {error}") from None
    summarize(study, args.env, output_folder(args))


if __name__ == "__main__":
    main(sys.argv[1:])
