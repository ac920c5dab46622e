"""The paper's first figure: return against training steps on "Retain the Almighty" for pre-assignment and for
selection without it, in sequence and in random order."""

from __future__ import annotations

import csv
from pathlib import Path

from sb3_taskalloc.experiments.evaluation import Curve
from sb3_taskalloc.experiments.plots import plot_almighty

VARIANTS = {
    "pre-assign (ours)": {},
    "sequence": {"preassign": False, "task_order": "sequential"},
    "random": {"preassign": False, "task_order": "random"},
}


def almighty_figure(seeds: int = 5, steps: int = 1200, every: int = 50, out: str | Path = "runs/almighty") -> Path:
    """Train the three variants (``learning_rate=1e-3``, ``learning_starts=200``, as the learning check) and write
    ``almighty.csv`` (variant, seed, step, return) and ``almighty.png`` (mean and range over seeds, optimum 35)."""
    from tqdm.auto import tqdm

    from sb3_taskalloc import TwoStageSAC

    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    curves: dict[str, list[list[tuple[int, float]]]] = {name: [] for name in VARIANTS}
    for name, kwargs in tqdm(list(VARIANTS.items()), desc="Almighty variants"):
        for seed in range(seeds):
            model = TwoStageSAC(
                "TAMPolicy", "TaskAlloc/Almighty-v0", learning_rate=1e-3, learning_starts=200, seed=seed, policy_kwargs=kwargs
            )
            callback = Curve("TaskAlloc/Almighty-v0", [0], every)  # the one-step episode of reset seed 0
            model.learn(steps, callback=callback)
            curves[name].append(callback.points)
    with (folder / "almighty.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["variant", "seed", "step", "return"])
        for name, runs in curves.items():
            for seed, points in enumerate(runs):
                writer.writerows([name, seed, step, value] for step, value in points)
    return plot_almighty(curves, folder / "almighty.png")
