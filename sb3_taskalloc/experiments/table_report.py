"""The paper's table of one env (:class:`.table.TableRun`) as files: ``table.csv``, ``table.md`` with the comparison's
goals, and ``curves.png``."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sb3_taskalloc.common.utils import atomic_path, atomic_write_text
from sb3_taskalloc.experiments.budgets import FOOTNOTES, METHODS, ROWS

if TYPE_CHECKING:
    from sb3_taskalloc.experiments.table import TableRun


def env_logs(log: Path, n_envs: int) -> list[Path]:
    """The Monitor logs of ``n_envs`` envs that train one model: ``log`` itself for one env, else one file per env
    beside it (``<stem>.env<k>.monitor.csv``)."""
    if n_envs == 1:
        return [log]
    stem = log.name.removesuffix(".monitor.csv")
    return [log.with_name(f"{stem}.env{k}.monitor.csv") for k in range(n_envs)]


def logged_returns(logs: list[Path]) -> np.ndarray:
    """Training episode returns in the order the episodes ended, merged by end time from the Monitor logs of the envs
    that trained one model (:func:`env_logs`); empty when there are none."""
    ends = []
    for path in (log for log in logs if log.exists()):
        for row in path.read_text().strip().splitlines()[2:]:  # Monitor: a JSON line, then the header r,l,t
            r, _, t = row.split(",")[:3]
            ends.append((float(t), float(r)))
    return np.array([r for _, r in sorted(ends)])


def _milp_gaps(run: TableRun) -> tuple[Path, dict[str, dict[str, float]]]:
    """``milp_gaps.json`` beside the cells and what it holds (empty before the first MILP cell)."""
    path = run.folder / "milp_gaps.json"
    return path, (json.loads(path.read_text()) if path.exists() else {})


def _milp_gap_key(run: TableRun, name: str, row: str, seed: int) -> str:
    """The key of one cell's gap: its row, seed and configuration (:meth:`~.table.TableRun.cell_key`)."""
    return f"{row}|{seed}|{run.cell_key(name, row)}"


def record_milp_gap(run: TableRun, name: str, row: str, seed: int, agent: object) -> None:
    """File the per-step MILP's :meth:`~sb3_taskalloc.baselines.MILPAllocator.gap_summary` of one cell in
    ``milp_gaps.json`` beside the cells, under the cell's configuration (other agents: nothing)."""
    from sb3_taskalloc.baselines import MILPAllocator

    if isinstance(agent, MILPAllocator):
        path, gaps = _milp_gaps(run)
        gaps[_milp_gap_key(run, name, row, seed)] = agent.gap_summary()
        atomic_write_text(path, json.dumps(gaps, indent=1) + "\n")


def milp_gap_line(run: TableRun) -> list[str]:
    """The table's line on how the per-step MILP stopped, over its finished cells of this configuration whose gap was
    filed (none: no line)."""
    from sb3_taskalloc.baselines import MILPAllocator

    _, gaps = _milp_gaps(run)
    keys = [_milp_gap_key(run, name, row, seed) for name, row, seed in run.done() if name == "MILP" and seed < run.seeds]
    g = MILPAllocator.pooled_gap_summary([gaps[k] for k in keys if k in gaps])
    if not g["solves"]:
        return []
    limits = run.budget.milp or "its defaults"
    return ["", f"MILP: HiGHS with {limits} per solve; {g['stopped']:.0%} of {int(g['solves'])} solves stopped short of "
            f"proven optimality, mean gap {g['mean_gap']:.4f}, largest {g['max_gap']:.4f}."]  # fmt: skip


#: The last line of a one-seed table: its columns carry no spread over training seeds to judge a difference by.
ONE_SEED = (
    "One training seed: the table has no spread over seeds, so a difference between two columns is not a result "
    "here (it may be the training's noise); `--seeds 5` gives each cell's mean ± std."
)


def write_table(run: TableRun) -> Path:
    """``table.csv`` (row, method, mean, std, n) and ``table.md`` (mean ± std, n/a with footnotes)."""
    done = run.done()
    notes: set[str] = set()
    summary: dict[tuple[str, str], str] = {}
    with atomic_path(run.folder / "table.csv") as tmp, tmp.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["row", "method", "mean", "std", "n"])
        for row in ROWS:
            for name in run.methods:
                values = [done[(name, row, s)] for s in range(run.seeds) if (name, row, s) in done]
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
        f"# {run.env}: return, mean ± std over {run.seeds} seeds (budget `{run.budget_name}`)"
        if run.seeds > 1
        else f"# {run.env}: return of one seed (budget `{run.budget_name}`)",
        "",
        f"Command: `python -m sb3_taskalloc.experiments table --env {run.env} --seeds {run.seeds} --budget "
        f"{run.budget_name}`. Budget: {run.budget}.",
        "",
        "| setting | " + " | ".join(run.methods) + " |",
        "|---|" + "---|" * len(run.methods),
    ]
    for row in ROWS:
        cells = [summary.get((row, name), "") for name in run.methods]
        if any(c and "(preset)" not in c for c in cells):
            lines.append(f"| {row} | " + " | ".join(cells) + " |")
    lines += ["", *[f"- {FOOTNOTES[k]}" for k in sorted(notes - {"preset"})], *milp_gap_line(run)]
    reached = goals(run)
    if reached:
        lines += ["", "Goals (ratios of the means above; higher is better):", "", *[f"- {g}" for g in reached]]
    if run.seeds == 1:  # without a spread over seeds a difference between two columns may be training noise
        lines += ["", ONE_SEED]
    path = atomic_write_text(run.folder / "table.md", "\n".join(lines) + "\n")
    return path


def means(run: TableRun) -> dict[tuple[str, str], float]:
    """(row, method) → mean over the finished seeds below ``seeds`` (numbers only), as in the table: cells of
    further seeds in ``cells.csv`` (a run with more seeds) do not enter a table of fewer."""
    done = run.done()
    out: dict[tuple[str, str], float] = {}
    for row in ROWS:
        for name in run.methods:
            numbers = [
                float(v)
                for (m, r, s), v in done.items()
                if m == name and r == row and s < run.seeds and not v.startswith("n/a")
            ]
            if numbers:
                out[(row, name)] = float(np.mean(numbers))
    return out


def goals(run: TableRun) -> list[str]:
    """The comparison's goals, as text lines: Ours / best of GA, PSO, SOS (goal ≥ 1.1), Ours / Greedy (≥ 1), Ours
    against both W/o Pre rows (above), and zero-shot / from scratch on each preset (≥ 0.8)."""
    mean = means(run)
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


def plot_curves(run: TableRun) -> Path | None:
    """``curves.png``: training episode returns of the RL methods, averaged over seeds (from the Monitor logs)."""
    from sb3_taskalloc.experiments.plots import plot_learning_curve

    curves: dict[str, np.ndarray] = {}
    for name in run.methods:
        runs = []
        for seed in range(run.seeds):
            returns = logged_returns(env_logs(run._log_path(name, seed), run._n_envs(METHODS[name])))
            if len(returns):
                runs.append(returns)
        if runs and min(len(r) for r in runs) > 0:
            n = min(len(r) for r in runs)
            curves[name] = np.mean([r[:n] for r in runs], axis=0)
    if not curves:
        return None
    return plot_learning_curve(curves, run.folder / "curves.png", title=f"{run.env}: training episodes ({run.budget_name})")
