"""Plots of the experiments (matplotlib, headless)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np


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
    curves: Mapping[str, np.ndarray],
    path: str | Path,
    title: str = "",
    baselines: Mapping[str, float] | None = None,
    xlabel: str = "episode",
) -> Path:
    """Episode returns (raw, faint; smoothed, solid) with horizontal lines for baselines. Returns the PNG path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for i, (name, values) in enumerate(curves.items()):
        color = f"C{i}"
        values = np.asarray(values, dtype=float)
        x = np.arange(1, len(values) + 1)
        ax.plot(x, values, color=color, alpha=0.25, lw=1)
        ax.plot(x, smooth(values), color=color, lw=2, label=name)
    for k, (name, value) in enumerate((baselines or {}).items()):
        ax.axhline(value, color=f"C{k + len(curves)}", ls="--", lw=1.5, label=f"{name} ({value:.1f})")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("return")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
