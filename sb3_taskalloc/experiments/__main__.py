"""``python -m sb3_taskalloc.experiments {table,almighty}``: the paper's results table and its first figure."""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> None:
    from sb3_taskalloc.experiments.budgets import BUDGETS, ENVS, METHODS

    parser = argparse.ArgumentParser(prog="python -m sb3_taskalloc.experiments", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    table = sub.add_parser("table", help="results table of one env (resumes from results/<env>/)")
    table.add_argument("--env", required=True, choices=ENVS)
    table.add_argument("--seeds", type=int, default=5)
    table.add_argument("--budget", default="local", choices=list(BUDGETS))
    table.add_argument("--out", default="results")
    table.add_argument(
        "--methods", nargs="+", default=None, choices=list(METHODS), metavar="METHOD", help=f"subset of {list(METHODS)}"
    )
    table.add_argument("--fresh", action="store_true", help="discard the env's previous cells and models")
    fig = sub.add_parser("almighty", help="return vs steps on Almighty: pre-assign, sequence, random (the paper's figure)")
    fig.add_argument("--seeds", type=int, default=5)
    fig.add_argument("--steps", type=int, default=1200)
    fig.add_argument("--every", type=int, default=50)
    fig.add_argument("--out", default="results/almighty")
    args = parser.parse_args(argv)

    import torch as th

    import envs  # noqa: F401  (registers the TaskAlloc ids)

    th.set_num_threads(1)
    if args.command == "almighty":
        from sb3_taskalloc.experiments.almighty import almighty_figure

        print(f"wrote {almighty_figure(args.seeds, args.steps, args.every, args.out)}")
        return
    if args.seeds < 1:
        parser.error(f"--seeds must be >= 1, got {args.seeds}")
    from sb3_taskalloc.experiments.table import TableRun

    if args.fresh:
        for name in ("cells.csv", "models", "logs"):
            path = Path(args.out) / args.env / name
            shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)
    path = TableRun(args.env, args.seeds, args.budget, args.out, args.methods).run()
    print(path.read_text())
    print(f"wrote {path}, {path.with_suffix('.csv')}")


if __name__ == "__main__":
    main(sys.argv[1:])
