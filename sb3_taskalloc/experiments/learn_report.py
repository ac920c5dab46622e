"""The learning experiment's report (:class:`.learn.LearnRun`): per seed, mean ± std, the critic's figures and the
targets, as Markdown, JSON and the curves' PNG."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sb3_taskalloc.common.utils import atomic_write_text
from sb3_taskalloc.experiments.evaluation import seed_mean

if TYPE_CHECKING:
    from sb3_taskalloc.experiments.learn import LearnRun

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
    "advantage_ties": "tied",
    "advantage_corr": "corr(ΔQ, ΔḠ)",
    "advantage_ceiling": "ΔḠ ceiling",
    "advantage_sign": "same sign",
}
CRITIC_BRANCHED = ["q_corr_expected", "q_scale_expected", "return_ceiling", "free_corr_q", "free_corr_expected"]
CRITIC_ADVANTAGE = ["advantage_pairs", "advantage_ties", "advantage_corr", "advantage_ceiling", "advantage_sign"]
#: Counts among the critic's figures (no decimals).
COUNTS = ("advantage_pairs", "advantage_ties")


def has_branched(records: list[dict[str, Any]], keys: list[str] = CRITIC_BRANCHED) -> bool:
    """Whether every record holds the critic's figures ``keys`` of the branched rollouts (:data:`CRITIC_BRANCHED`, or
    :data:`CRITIC_ADVANTAGE`: each set came with a later version of :mod:`.diagnose`)."""
    return all(k in r for r in records for k in keys)


def critic_trained(records: list[dict[str, Any]]) -> bool:
    """Whether the records hold figures of a trained stage-1 critic (none without pre-assignment, or with its actor
    held at its rule: NaN)."""
    return any(math.isfinite(r.get("q_corr", math.nan)) for r in records)


def _row(cells: list[str]) -> str:
    """One markdown table row of ``cells`` (an empty list of critic columns adds no empty cell)."""
    return "| " + " | ".join(cells) + " |"


def machines(records: list[dict[str, Any]]) -> str:
    """Where the seeds were measured, each machine once (records of earlier versions carry none)."""
    seen = sorted(
        {
            f"{m['cpu']} ({m['cpu_capability']})"
            + (f" and {m['gpu']}" if m["gpu"] and record.get("device") == "cuda" else "")
            + f", torch {m['torch']}, stable-baselines3 {m['libraries']['stable-baselines3']}"
            for record in records
            if (m := record.get("machine"))
        }
    )
    return f" Measured on {'; '.join(seen)}." if seen else ""


def _seed_mean_cell(records: list[dict[str, Any]], name: str, digits: int = 2) -> str:
    """:func:`seed_mean` formatted, with the number of seeds it is over when some seeds lack the figure ("—" when none
    has it)."""
    mean, defined = seed_mean(records, name)
    if not defined:
        return "—"
    return f"{mean:.{digits}f}" + (f" ({defined} of {len(records)} seeds)" if defined < len(records) else "")


def write(run: LearnRun, records: list[dict[str, Any]]) -> Path:
    """``<out>/<env>.json`` (per seed), ``.png`` (curves) and ``.md`` (per seed, mean ± std, targets)."""
    from sb3_taskalloc.experiments.plots import plot_learning_progress

    selected = ["best"] if all("best" in r for r in records) else []
    stages = ["actor_only", "pointer_only"] if all("actor_only" in r for r in records) else []
    dagger = ["before_dagger"] if all("before_dagger" in r for r in records) else []
    columns = ["untrained", "trained", *dagger, *stages, *selected, "Greedy", "MILP", *run.planners]
    means = {c: [float(np.mean(r[c])) for r in records] for c in columns}
    best_planner = max(run.planners, key=lambda p: float(np.mean(means[p]))) if run.planners else None
    stem = Path(run.out) / run.env
    atomic_write_text(stem.with_suffix(".json"), json.dumps({"settings": run.describe(), "seeds": records}) + "\n")
    png = plot_learning_progress(
        {r["seed"]: r["curve"] for r in records},
        {"Greedy": float(np.mean(means["Greedy"])), "MILP": float(np.mean(means["MILP"]))},
        stem.with_suffix(".png"),
        f"{run.env_id}: deterministic return on {'validation' if run.validation_episodes else 'held-out'} episodes "
        "while training",
        marks={f"DAgger ({run.select_dagger} iterations) from here": run.steps} if dagger else None,
    )
    shown = ["untrained", "trained", *dagger, *stages, *selected, "Greedy", "MILP"]
    shown += [best_planner] if best_planner else []
    names = {"best": "best on validation", "actor_only": "only actor learned", "pointer_only": "only pointer learned",
             "before_dagger": "before DAgger"}  # fmt: skip
    headers = [names.get(c, c) for c in shown]
    critic = ["q_corr", "q_scale", *(CRITIC_BRANCHED if has_branched(records) else [])]
    critic += CRITIC_ADVANTAGE if has_branched(records, CRITIC_ADVANTAGE) else []
    critic = critic if critic_trained(records) else []
    header = ["seed", *headers, *(CRITIC_COLUMNS[c] for c in critic), "training s"]
    first, last = run.seed_range[0], run.seed_range[-1]
    span = f"{first}" if first == last else f"{first}–{last}"
    lines = [
        f"# {run.env_id}: TwoStageSAC trained {run.steps:,} steps, {len(records)} seed{'s' if len(records) > 1 else ''}"
        + (f" ({span})" if run.first_seed else "")
        + f" × {run.eval_episodes} held-out episodes"
        + (" (trained on CUDA)" if run.device == "cuda" else ""),
        "",
        f"Command: `{run.command()}`. Curve: `{png.name}`." + machines(records),
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
                f"Trained: {run.steps:,} steps of TwoStageSAC, then {run.select_dagger} DAgger iterations teaching "
                "the pointer the exact cover of its candidates (`TwoStageSAC.distill_select`"
                + (f", teacher `{run.dagger_kwargs['teacher']}`" if "teacher" in run.dagger_kwargs else "")
                + "); before DAgger: the model after the steps alone.",
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
        _row(header),
        "|---" * len(header) + "|",
    ]
    for k, r in enumerate(records):
        figures = [f"{r[c]:.0f}" if c in COUNTS else f"{r[c]:.2f}" for c in critic]
        lines.append(_row([str(r["seed"]), *(f"{means[c][k]:.1f}" for c in shown), *figures, f"{r['train_seconds']:.0f}"]))
    summary = [f"{np.mean(means[c]):.1f} ± {np.std(means[c]):.1f}" for c in shown]
    critic_means = [_seed_mean_cell(records, c, 1 if c in COUNTS else 2) for c in critic]
    lines.append(_row(["mean ± std", *summary, *critic_means, ""]))
    lines += ["", *targets(run, means, records)]
    return atomic_write_text(stem.with_suffix(".md"), "\n".join(lines) + "\n")


def milp_gap(run: LearnRun, records: list[dict[str, Any]]) -> str:
    """How the per-step MILP reference stopped, over every seed's solves (records of earlier versions have no gap)."""
    from sb3_taskalloc.baselines import MILPAllocator

    gaps = [r["MILP gap"] for r in records if "MILP gap" in r]
    if not gaps:
        return ""
    g = MILPAllocator.pooled_gap_summary(gaps)
    return (f"; the MILP stops at {run.milp_node_limit} HiGHS nodes per solve: {g['stopped']:.0%} of {int(g['solves'])} "
            f"solves short of proven optimality, mean gap {g['mean_gap']:.4f}, largest {g['max_gap']:.4f}")  # fmt: skip


def critic_lines(records: list[dict[str, Any]]) -> list[str]:
    """The stage-1 critic's figures against their targets, or that it did not train."""
    if not critic_trained(records):
        held = "its actor held at its rule with the AMIX critic: `train_preassign_actor=False`"
        return [f"- critic: not trained (no pre-assignment, or {held})"]
    n = len(records)
    corr = np.array([r["q_corr"] for r in records])
    scale = np.array([r["q_scale"] for r in records])
    timings = " / ".join(sorted({r.get("critic_reward", "completion") for r in records}))
    paired = {c: seed_mean(records, c) for c in CRITIC_ADVANTAGE} if has_branched(records, CRITIC_ADVANTAGE) else {}
    return [
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
                f"the pairs whose returns differ ({sum(r['advantage_ties'] for r in records)} of the pairs returned the "
                "same in every branch)"
                + (
                    f" (means over the {paired['advantage_corr'][1]} of {n} seeds with such pairs)"
                    if paired["advantage_corr"][1] < n
                    else ""
                ),
            ]
            if paired
            else []
        ),
    ]


def targets(run: LearnRun, means: dict[str, list[float]], records: list[dict[str, Any]]) -> list[str]:
    """The learning targets, each with its measured value."""
    trained, init, greedy, milp = (np.array(means[c]) for c in ("trained", "untrained", "Greedy", "MILP"))
    n = len(trained)
    ratio = trained.mean() / init.mean() if init.mean() > 0 else float("nan")
    milp_target = " (target ≥ 0.99)" if run.env == "EPT" else " (goal ≥ 1)"
    lines = [
        f"- trained / untrained (means): {ratio:.3f} (target ≥ 1.10)",
        f"- trained > untrained: {int((trained > init).sum())} of {n} seeds (target ≥ 4 of 5)",
        f"- trained > Greedy: {int((trained > greedy).sum())} of {n} seeds (target all)",
        f"- trained / per-step MILP (means): {trained.mean() / milp.mean():.3f}{milp_target}{milp_gap(run, records)}",
        *critic_lines(records),
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


def diagnose_record(run: LearnRun, model: Any, seed: int) -> dict[str, Any]:
    """The critic's calibration and the sampled return of the trained model (:func:`.diagnose.diagnose`)."""
    from sb3_taskalloc.experiments.diagnose import diagnose

    d = diagnose(model, run.env_id, episodes=min(3, run.eval_episodes), seed=20_000 + 100 * seed)
    branched = {k: getattr(d, k) for k in [*CRITIC_BRANCHED, *CRITIC_ADVANTAGE]}
    return dict(q_corr=d.q_corr, q_scale=d.q_scale, sampled=d.sampled_return, critic_reward=d.reward_timing, **branched)


def complete_record(run: LearnRun, record: dict[str, Any], path: Path) -> dict[str, Any]:
    """A finished seed, with what later versions measure added from its saved model (and saved):

    - a record without ``critic_reward`` had its critic compared with returns of the env reward. That is the
      critic's own reward unless it learned the commitment reward: then the figures are measured again;
    - a record without ``actor_only`` gets the returns of :func:`.diagnose.stage_returns`;
    - a record without the figures of :data:`CRITIC_BRANCHED` or :data:`CRITIC_ADVANTAGE` gets them, the critic
      against the expected return (the same seeded diagnosis, so its other critic figures come out as they were).

    Where the model is gone the record stays as it is (with a warning when its critic figures are wrong).
    """
    stale = "critic_reward" not in record and run.hyperparameters.get("reward_timing", "completion") == "commitment"
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
        record = {**record, **diagnose_record(run, model, record["seed"])}
    if "actor_only" not in record:
        record = {**record, **stage_returns(model, run.env_id, record["eval_seeds"])}
    atomic_write_text(path, json.dumps(record) + "\n")
    return record
