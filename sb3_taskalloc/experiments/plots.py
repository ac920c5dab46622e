"""Every figure of the experiments (matplotlib, headless): learning curves, the Almighty figure, market incomes, the
critic's diagnosis."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from sb3_taskalloc.common.utils import atomic_path


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the headless Agg backend (imported on first use: the library never needs it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: str | Path, dpi: int = 110) -> Path:
    """Lay out, write (creating the folder) and close ``fig``; returns the path."""
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
    pyplot().close(fig)
    return Path(path)


def smooth(values: np.ndarray, window: int = 11) -> np.ndarray:
    """Centred moving average that works for any length (shrinks the window at the ends and for short series)."""
    values = np.asarray(values, dtype=float)
    if len(values) == 0:
        return values
    half = max(1, min(window, len(values))) // 2
    csum = np.concatenate([[0.0], np.cumsum(values)])
    idx = np.arange(len(values))
    lo, hi = np.maximum(idx - half, 0), np.minimum(idx + half + 1, len(values))
    return (csum[hi] - csum[lo]) / (hi - lo)


def plot_learning_curve(
    curves: Mapping[str, np.ndarray | tuple[np.ndarray, np.ndarray]],
    path: str | Path,
    title: str = "",
    baselines: Mapping[str, float] | None = None,
    xlabel: str = "episode",
    points: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
) -> Path:
    """Returns (raw, faint; smoothed, solid) with horizontal lines for baselines. Returns the PNG path.

    :param curves: name -> returns in order (x = 1, 2, ...) or (x, returns)
    :param points: name -> (x, values) drawn as they are, with markers (e.g. periodic evaluations)
    """
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    for i, (name, values) in enumerate(curves.items()):
        color = f"C{i}"
        x, y = values if isinstance(values, tuple) else (np.arange(1, len(values) + 1), values)
        y = np.asarray(y, dtype=float)
        ax.plot(x, y, color=color, alpha=0.25, lw=1)
        ax.plot(x, smooth(y), color=color, lw=2, label=name)
    for i, (name, (x, y)) in enumerate((points or {}).items(), start=len(curves)):
        ax.plot(x, y, color=f"C{i}", lw=2, marker="o", ms=4, label=name)
    n_lines = len(curves) + len(points or {})
    for k, (name, value) in enumerate((baselines or {}).items()):
        ax.axhline(value, color=f"C{k + n_lines}", ls="--", lw=1.5, label=f"{name} ({value:.1f})")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("return")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    return save_figure(fig, path)


def plot_incomes(history: list[dict[str, float]], path: str | Path, title: str = "") -> Path:
    """Manager, worker and total income per episode (the paper's RBF figure f), the workers' mean bid on a second axis."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    ep = np.arange(len(history))
    for key, label in (("total_income", "total"), ("manager_income", "manager"), ("worker_income", "workers")):
        ax.plot(ep, [h[key] for h in history], label=label)
    ax.set_xlabel("episode")
    ax.set_ylabel("income per episode")
    ax2 = ax.twinx()
    ax2.plot(ep, [h["mean_bid"] for h in history], color="grey", linestyle=":", label="mean bid")
    ax2.set_ylabel("mean bid")
    lines = ax.get_legend_handles_labels()
    lines2 = ax2.get_legend_handles_labels()
    ax.legend(lines[0] + lines2[0], lines[1] + lines2[1], loc="best")
    ax.set_title(title)
    return save_figure(fig, path, dpi=120)


def plot_almighty(curves: Mapping[str, list[list[tuple[int, float]]]], path: str | Path, optimum: float = 35.0) -> Path:
    """Deterministic return against env steps on Almighty for each variant: mean and range over seeds, and the optimum.

    :param curves: variant -> one list of (step, return) points per seed
    """
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    n_seeds = 0
    for i, (name, runs) in enumerate(curves.items()):
        n = min(len(r) for r in runs)
        x = np.array([p[0] for p in runs[0][:n]])
        y = np.array([[p[1] for p in r[:n]] for r in runs])
        ax.plot(x, y.mean(0), color=f"C{i}", lw=2, label=name)
        ax.fill_between(x, y.min(0), y.max(0), color=f"C{i}", alpha=0.15)
        n_seeds = len(runs)
    ax.axhline(optimum, color="k", ls="--", lw=1, label=f"optimum ({optimum:g})")
    ax.set_xlabel("env steps")
    ax.set_ylabel("deterministic return")
    ax.set_title(f"Retain the Almighty: mean and range over {n_seeds} seeds")
    ax.legend(loc="lower right")
    ax.grid(alpha=0.3)
    return save_figure(fig, path)


def plot_learning_progress(
    curves: Mapping[int, list[tuple[int, float]]],
    baselines: Mapping[str, float],
    path: str | Path,
    title: str = "",
    marks: Mapping[str, float] | None = None,
) -> Path:
    """Deterministic return against env steps: one faint line per seed, their mean, and horizontal baselines.

    :param curves: seed -> (step, return) points
    :param marks: label -> env step of a vertical line (where a phase of training begins)
    """
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    runs = [np.asarray(points, dtype=float) for points in curves.values() if len(points)]
    for run in runs:
        ax.plot(run[:, 0], run[:, 1], color="C0", alpha=0.3, lw=1)
    if runs:
        n = min(len(r) for r in runs)
        ax.plot(
            runs[0][:n, 0],
            np.mean([r[:n, 1] for r in runs], axis=0),
            color="C0",
            lw=2,
            label=f"TwoStageSAC ({len(runs)} seeds)",
        )
    for k, (name, value) in enumerate(baselines.items()):
        ax.axhline(value, color=f"C{k + 1}", ls="--", lw=1.5, label=f"{name} ({value:.1f})")
    for name, step in (marks or {}).items():
        ax.axvline(step, color="grey", ls=":", lw=1.5, label=name)
    ax.set_xlabel("env steps")
    ax.set_ylabel("deterministic return")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    return save_figure(fig, path)


def plot_critic(
    states: list[tuple[float, float]],
    pairs: list[tuple[float, float]],
    path: str | Path,
    title: str = "",
    labels: tuple[str, str] = ("", ""),
) -> Path:
    """Two scatters of the diagnosis: Q(s, c) against the expected return Ḡ of each branched state (does the critic
    value states?) and Q(s, c) − Q(s, c′) against ΔḠ of each pair of decisions of one state (does it rank decisions,
    what the pre-assign actor's gradient follows?), each with the diagonal of a critic on Ḡ's scale.

    :param labels: each panel's figures (correlation, ceiling)
    """
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    panels = (("states", "Ḡ (mean of the branches)", "Q(s, c)"), ("decision pairs", "ΔḠ", "ΔQ"))
    for ax, points, (name, x, y), label in zip(axes, (states, pairs), panels, labels, strict=True):
        xy = np.asarray(points, dtype=float).reshape(-1, 2)
        ax.scatter(xy[:, 1], xy[:, 0], s=14, alpha=0.7, color="C0")
        if len(xy):
            lo, hi = float(xy.min()), float(xy.max())
            ax.plot([lo, hi], [lo, hi], color="grey", ls=":", lw=1)
        ax.axhline(0, color="grey", lw=0.5)
        ax.axvline(0, color="grey", lw=0.5)
        ax.set_xlabel(x)
        ax.set_ylabel(y)
        ax.set_title(f"{name} ({len(xy)}): {label}", fontsize=9)
        ax.grid(alpha=0.3)
    fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)
