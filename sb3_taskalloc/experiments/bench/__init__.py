"""Benchmarks: ``python -m sb3_taskalloc.bench {envs,policy,train,zoo,baselines,learn,labels,all} [--out DIR]``.

Each benchmark prints a table and writes ``<out>/bench_<name>.json`` with the figures, the machine and the command.
Figures are measured with one thread (``OMP_NUM_THREADS=1``, ``torch.set_num_threads(1)``) unless stated. One module per
subject: :mod:`.envs` (envs and baselines), :mod:`.policy` (decisions), :mod:`.training` (training and learning).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import shlex
import sys
from typing import Any

from sb3_taskalloc.common.utils import atomic_write_text, writable_folder
from sb3_taskalloc.experiments.bench.common import BenchFn
from sb3_taskalloc.experiments.bench.envs import bench_baselines, bench_envs
from sb3_taskalloc.experiments.bench.policy import MT_DECODER, SEARCH, TEAM_SEARCH, bench_labels, bench_policy
from sb3_taskalloc.experiments.bench.training import LEARN_TARGET, bench_learn, bench_train, bench_zoo
from sb3_taskalloc.experiments.evaluation import machine

__all__ = ["LEARN_TARGET", "MT_DECODER", "SEARCH", "TEAM_SEARCH", "main"]


BENCHES: dict[str, BenchFn] = {
    "envs": bench_envs,
    "policy": bench_policy,
    "train": bench_train,
    "zoo": bench_zoo,
    "baselines": bench_baselines,
    "learn": bench_learn,
    "labels": bench_labels,
}


def _print_table(name: str, rows: list[dict[str, Any]]) -> None:
    if not rows:
        return
    keys = list(dict.fromkeys(key for row in rows for key in row))  # every column, in order of first appearance
    print(f"\n## {name}")
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for row in rows:
        cells = [_cell(row.get(key)) for key in keys]
        print("| " + " | ".join(cells) + " |")


def _cell(v: Any) -> str:
    """A table cell: 3 significant digits below 100, whole numbers above, blank for a missing value."""
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:,.3g}" if abs(v) < 100 else f"{v:,.0f}"
    if isinstance(v, list) and len(v) > 4:  # a curve: in the JSON
        return f"{len(v)} points"
    return str(v)


def build_parser() -> argparse.ArgumentParser:
    """The benchmarks' command line."""
    from sb3_taskalloc.experiments.budgets import yaml_mapping

    parser = argparse.ArgumentParser(
        formatter_class=argparse.ArgumentDefaultsHelpFormatter, prog="python -m sb3_taskalloc.bench", description=__doc__
    )
    parser.add_argument("which", choices=[*BENCHES, "all"], help="benchmark to run")
    parser.add_argument("--out", default="runs/bench", help="folder for the JSON results")
    parser.add_argument("--quick", action="store_true", help="shorter timings (smoke runs)")
    parser.add_argument(
        "--model", default=None, help="policy and labels benchmarks: a trained TwoStageSAC for the episode states"
    )
    parser.add_argument(
        "--train-steps",
        type=int,
        default=None,
        help="policy and labels benchmarks without --model: steps to train one first (default 3,000; 100 with --quick)",
    )
    parser.add_argument("--seeds", type=int, default=1, help="learn benchmark: training seeds 0 .. seeds - 1")
    parser.add_argument("--learn-steps", type=int, default=48_000, help="learn benchmark: env steps at most per seed")
    parser.add_argument("--eval-every", type=int, default=4_000, help="learn benchmark: env steps between evaluations")
    parser.add_argument(
        "--algo-kwargs",
        type=yaml_mapping,
        default={},
        help="learn and zoo benchmarks: TwoStageSAC keywords over the zoo config",
    )
    parser.add_argument(
        "--device",
        default="auto",
        choices=["auto", "cpu", "cuda"],
        help="devices for the policy and train benchmarks: auto = the CPU, plus CUDA when a GPU is available",
    )
    return parser


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    names = list(BENCHES) if args.which == "all" else [args.which]
    out = writable_folder(args.out)  # before the benchmarks, some of which take minutes
    for k, name in enumerate(names, 1):
        print(f"benchmark {name} ({k} of {len(names)}): running", flush=True)  # some take minutes before their table
        rows = BENCHES[name](args)
        _print_table(name, rows)
        record = {
            "benchmark": name,
            "command": "python -m sb3_taskalloc.bench " + shlex.join(sys.argv[1:] if argv is None else argv),
            "machine": machine(),
            "torch_threads": torch.get_num_threads(),
            "results": rows,
        }
        atomic_write_text(out / f"bench_{name}.json", json.dumps(record, indent=2))  # a kill leaves the last one whole
        print(f"wrote {out / f'bench_{name}.json'}")
