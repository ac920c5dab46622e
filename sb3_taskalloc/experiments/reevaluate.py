"""Re-evaluations of a finished learning experiment (:class:`.learn.LearnRun`): its trained models zero-shot on another
env, decoded by another strategy, or on further held-out episodes, against the same policy untrained and the
baselines; each seed's row is saved as it finishes."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
from tqdm.auto import tqdm

from sb3_taskalloc.common.utils import atomic_write_text, check_counts
from sb3_taskalloc.experiments import evaluation
from sb3_taskalloc.experiments.evaluation import EPISODES_PER_SEED, decision_digest, eval_seeds

if TYPE_CHECKING:
    from sb3_taskalloc.experiments.learn import LearnRun


def _reevaluation_labels(shift: str | None, decoder: str, config: dict[str, Any], more_episodes: int) -> tuple[str, str, str]:
    """The file-name suffix, the title's words and the command-line flags of a :meth:`LearnRun.reevaluate`, from its
    parts in one order: the shift, the decoding strategy unless it is the argmax, the further episodes."""
    parts: list[tuple[str, str]] = []  # (file-name part, flag) of each part that is on
    if shift:
        parts.append((f"zero_shot_{shift}", f"zero-shot {shift}"))
    if decoder != "argmax":
        # a sequence setting (entity_value's theta) joins its numbers with "_": no brackets or spaces in a file name
        text = {k: "_".join(map(str, v)) if isinstance(v, list | tuple) else v for k, v in config.items()}
        settings = "".join(f"_{k}_{v}" for k, v in sorted(text.items()))
        flag = f"decoder {decoder}" + (f" --decoder-kwargs '{json.dumps(config)}'" if config else "")
        parts.append((f"decoder_{decoder}{settings}", flag))
    if more_episodes:
        parts.append((f"more_episodes_{more_episodes}", f"more-episodes {more_episodes}"))
    if not more_episodes:
        first = "zero-shot" if shift else "held-out episodes"
    elif shift:
        first = f"zero-shot, {more_episodes} further episodes per seed"
    else:
        first = f"{more_episodes} further held-out episodes per seed"
    words = [first] if decoder == "argmax" else [first, f"decoded by {decoder} {config or ''}".rstrip()]
    return "".join(f"_{part}" for part, _ in parts), ", ".join(words), "".join(f" --{flag}" for _, flag in parts)


def reevaluate(
    run: LearnRun,
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
        env or of ``shift`` (the reset seeds that follow the run's own, :func:`eval_seeds`), against Greedy only; the
        report also counts the seeds above Greedy over all the run's (or its zero-shot's) and the further episodes,
        whose seed means carry a smaller standard error than the run's own (``<out>/<env>[_zero_shot_<shift>]
        _more_episodes_<N>``; with a shift, after the zero-shot re-evaluation itself)
    :return: the Markdown path."""
    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc import baselines as b
    from sb3_taskalloc.two_stage_sac.decoding import get_decoding_strategy

    env_id = f"TaskAlloc/{shift}-v0" if shift else run.env_id
    config = dict(decoder_kwargs or {})
    strategy = get_decoding_strategy(decoder, **config)  # a bad name or setting fails before any evaluation
    check_more_episodes(run, more_episodes)
    if more_episodes and decoder != "argmax":
        raise ValueError("more_episodes evaluates the plain argmax: no decoder")
    suffix, how, flags = _reevaluation_labels(shift, decoder, config, more_episodes)
    stem = Path(run.out) / (run.env + suffix)  # a setting's number may hold a dot: the suffixes are appended, not replaced
    rows: list[dict[str, Any]] = []
    for seed in tqdm(run.seed_range, desc=f"{run.env} re-evaluation, {how}"):
        path = run.seed_path(seed).with_suffix(".zip")
        if not path.exists():
            raise FileNotFoundError(f"seed {seed} has no trained model at {path}: run the experiment first")
        model_digest = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
        trained = TwoStageSAC.load(path, env=gym.make(env_id), device="cpu")
        trained.set_decoder(decoder, **config)
        decisions = decision_digest(trained, env_id)
        done = _row_path(run, stem.name, seed)
        saved = json.loads(done.read_text()) if done.exists() else {}
        if saved.get("model_digest") == model_digest and saved.get("decisions") == decisions:
            rows.append(saved)
            continue
        seeds = eval_seeds(seed, run.eval_episodes + more_episodes)[run.eval_episodes if more_episodes else 0 :]
        untrained = TwoStageSAC(
            "TAMPolicy",
            env_id,
            seed=seed,
            device="cpu",
            policy_kwargs=trained.policy_kwargs,
            train_preassign_actor=trained.train_preassign_actor,
        )
        untrained.set_decoder(get_decoding_strategy(decoder, **config))
        row = {"seed": seed, "trained": evaluation.episode_returns(trained, env_id, seeds),
               "untrained": evaluation.episode_returns(untrained, env_id, seeds)}  # fmt: skip
        if shift or more_episodes:  # the per-step MILP takes seconds per step: the training env's held-out episodes only
            row["Greedy"] = evaluation.episode_returns(b.GreedyAllocator(), env_id, seeds)
        else:
            row.update(run.baselines(seed))
        row["model_digest"], row["decisions"] = model_digest, decisions
        atomic_write_text(done, json.dumps(row) + "\n")
        rows.append(row)
    settings = {"settings": run.describe(), "env": env_id, "decoder": repr(strategy), "seeds": rows}
    atomic_write_text(stem.with_name(stem.name + ".json"), json.dumps(settings))
    title = f"# {env_id}: {how}, the models of `{run.env}.md` ({run.steps:,} steps on {run.env_id})"
    lines = [title, "", f"Command: `{run.command()}{flags}`", *report_lines(rows, with_milp=not (shift or more_episodes))]
    lines += over_all_episodes(run, rows, shift) if more_episodes else []
    return atomic_write_text(stem.with_name(stem.name + ".md"), "\n".join(lines) + "\n")


def report_lines(rows: list[dict[str, Any]], with_milp: bool) -> list[str]:
    """The re-evaluation's table (per seed, mean ± std) and its comparisons, as Markdown lines."""
    columns = ["untrained", "trained", "Greedy", *(["MILP"] if with_milp else [])]
    means = {c: np.array([np.mean(r[c]) for r in rows]) for c in columns}
    lines = [
        "",
        "| seed | " + " | ".join(columns) + " |",
        "|---" * (len(columns) + 1) + "|",
        *(f"| {r['seed']} | " + " | ".join(f"{means[c][k]:.1f}" for c in columns) + " |" for k, r in enumerate(rows)),
        "| mean ± std | " + " | ".join(f"{means[c].mean():.1f} ± {means[c].std():.1f}" for c in columns) + " |",
        "",
        f"- trained ≥ Greedy: {int((means['trained'] >= means['Greedy']).sum())} of {len(rows)} seeds (target all)",
        f"- trained > untrained: {int((means['trained'] > means['untrained']).sum())} of {len(rows)} seeds, "
        f"{means['trained'].mean() / means['untrained'].mean():.3f} × (means)",
    ]
    if with_milp:
        lines.append(f"- trained / per-step MILP (means): {means['trained'].mean() / means['MILP'].mean():.3f}")
    return lines


def check_more_episodes(run: LearnRun, more_episodes: int) -> None:
    """A clear error where :meth:`reevaluate`'s ``more_episodes`` is neither 0 (off) nor a positive integer, or would
    reach into the next training seed's held-out reset seeds (each seed has :data:`EPISODES_PER_SEED`)."""
    if more_episodes:
        check_counts({"more_episodes": more_episodes})
    if run.eval_episodes + more_episodes > EPISODES_PER_SEED:
        raise ValueError(
            f"eval_episodes + more_episodes must be at most {EPISODES_PER_SEED} (each seed's share of the held-out "
            f"reset seeds), got {run.eval_episodes} + {more_episodes}"
        )


def _row_path(run: LearnRun, stem_name: str, seed: int) -> Path:
    """Where a re-evaluation named ``stem_name`` (:func:`_reevaluation_labels`' suffix after the env) saves ``seed``'s row."""
    return run.seed_path(seed).with_name(f"{stem_name}_seed_{seed}_{run.key}.json")


def _own_path(run: LearnRun, seed: int, shift: str | None) -> Path:
    """The seed's saved row of the run's own held-out episodes: the run's, or with ``shift`` its zero-shot's."""
    if not shift:
        return run.seed_path(seed)
    path = _row_path(run, run.env + _reevaluation_labels(shift, "argmax", {}, 0)[0], seed)
    if not path.exists():
        raise FileNotFoundError(f"seed {seed} has no zero-shot row at {path}: run the zero-shot re-evaluation first")
    return path


def over_all_episodes(run: LearnRun, rows: list[dict[str, Any]], shift: str | None = None) -> list[str]:
    """The report's lines of :meth:`reevaluate`'s ``more_episodes``: each seed over the run's own held-out episodes
    (with ``shift``, its zero-shot re-evaluation's) and the further ones together, with the standard error of its mean
    lead over Greedy (paired by episode)."""
    header = "| seed | episodes | untrained | trained | Greedy | trained − Greedy ± s.e. |"
    lines = ["", "Over the run's own and the further held-out episodes together:", "", header, "|---" * 6 + "|"]
    leads, gains = [], []
    for row in rows:
        own = json.loads(_own_path(run, row["seed"], shift).read_text())
        if own.get("model_digest", row["model_digest"]) != row["model_digest"]:  # the run's own rows carry none
            raise ValueError(f"seed {row['seed']}'s zero-shot row is of another model: run the zero-shot re-evaluation again")
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
