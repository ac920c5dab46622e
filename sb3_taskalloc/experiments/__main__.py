"""``python -m sb3_taskalloc.experiments {table,almighty,diagnose,learn}``: the paper's results table, its first figure, and
what a model's critic and actor are doing."""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path
from typing import Any

import envs
from sb3_taskalloc.common.utils import writable_folder
from sb3_taskalloc.experiments.budgets import BUDGETS, ENVS, METHODS, env_name, yaml_mapping

#: Every command's ``--help`` shows the defaults.
DEFAULTS = argparse.ArgumentDefaultsHelpFormatter
#: The envs that ``learn`` and ``diagnose`` take: every registered one, so a shifted env's own block is measured on it
#: too (the paper's table has its four).
REGISTERED_ENVS = sorted(env_name(env_id) for env_id in envs.ENV_SPECS)


def build_parser() -> argparse.ArgumentParser:
    """The command line of every experiment."""
    parser = argparse.ArgumentParser(
        formatter_class=argparse.ArgumentDefaultsHelpFormatter, prog="python -m sb3_taskalloc.experiments", description=__doc__
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (_add_table, _add_almighty, _add_diagnose, _add_learn):
        add(sub)
    return parser


def _add_table(sub: Any) -> None:
    table = sub.add_parser(
        "table",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        help="results table of one env (resumes from <out>/<env>/)",
    )
    table.add_argument("--env", required=True, type=env_name, choices=ENVS)
    table.add_argument("--seeds", type=int, default=5, help="training seeds per cell")
    table.add_argument("--budget", default="local", choices=list(BUDGETS))
    table.add_argument("--out", default="runs/tables", help="where the tables go (results/ only when asked)")
    table.add_argument(
        "--methods", nargs="+", default=None, choices=list(METHODS), metavar="METHOD", help=f"subset of {list(METHODS)}"
    )
    table.add_argument("--fresh", action="store_true", help="discard the env's previous cells and models")


def _add_almighty(sub: Any) -> None:
    fig = sub.add_parser(
        "almighty",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        help="return vs steps on Almighty: pre-assign, sequence, random (the paper's figure)",
    )
    fig.add_argument("--seeds", type=int, default=5, help="training seeds")
    fig.add_argument("--steps", type=int, default=1200, help="env steps per seed")
    fig.add_argument("--every", type=int, default=50, help="env steps between evaluations")
    fig.add_argument("--out", default="runs/almighty", help="output folder")


def _add_diagnose(sub: Any) -> None:
    diag = sub.add_parser(
        "diagnose",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        help="critic calibration, entropy bonus, KL to the initial rule, sampled vs argmax return",
    )
    diag.add_argument("--env", required=True, type=env_name, choices=REGISTERED_ENVS)
    diag.add_argument("--model", default=None, help="a saved TwoStageSAC (default: a new one, trained for --steps)")
    diag.add_argument("--steps", type=int, default=0, help="env steps to train a new model first (0: untrained)")
    diag.add_argument("--episodes", type=int, default=3, help="sampled and deterministic evaluation episodes each")
    diag.add_argument("--seed", type=int, default=0, help="training seed (evaluation seeds start at 10,000)")
    diag.add_argument("--branches", type=int, default=8, help="rollouts per branched state for corr(Q, Ḡ) (0: skip)")
    diag.add_argument("--branch-stride", type=int, default=10, help="branch every this many steps of an episode")
    diag.add_argument("--out", default="runs/diagnose", help="output folder")
    diag.add_argument(
        "--algo-kwargs", type=yaml_mapping, default={}, help='TwoStageSAC keywords, e.g. "{entropy_bonus: mean}"'
    )


def _add_learn(sub: Any) -> None:
    learn = sub.add_parser(
        "learn",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        help="trained vs untrained, Greedy, per-step MILP and planners, per seed (resumes)",
    )
    learn.add_argument("--env", required=True, type=env_name, choices=REGISTERED_ENVS)
    learn.add_argument("--seeds", type=int, default=5, help="training seeds")
    learn.add_argument(
        "--first-seed", type=int, default=0, metavar="S",
        help="train seeds S .. S + seeds - 1 (a replicate on new seeds and new held-out episodes; default 0)",
    )  # fmt: skip
    learn.add_argument(
        "--device", choices=("cpu", "cuda"), default="cpu",
        help="where the seeds train (evaluated on the CPU either way; a CUDA run has its own seed files)",
    )  # fmt: skip
    learn.add_argument("--steps", type=int, default=20_000, help="training env steps per seed (0: with --select-dagger only)")
    learn.add_argument("--eval-episodes", type=int, default=10, help="held-out evaluation episodes per seed")
    learn.add_argument("--eval-every", type=int, default=2_000, help="env steps between the curve's evaluations")
    learn.add_argument(
        "--validation-episodes",
        type=int,
        default=0,
        help="curve on this many validation episodes per seed, and its best checkpoint evaluated too (0: off)",
    )
    learn.add_argument(
        "--select-dagger", type=int, default=None, metavar="N",
        help="after the steps, N DAgger iterations teaching the pointer the exact cover of its candidates (0: off; "
        "default: the zoo block's SelectDAggerCallback, off without one)",
    )  # fmt: skip
    learn.add_argument(
        "--dagger-imitation", choices=("sequence", "set"), default=None,
        help="DAgger's loss: each labelled pick in the label's order, or any member of the cover not picked yet "
        "(default: the zoo block's, else sequence)",
    )  # fmt: skip
    learn.add_argument("--planners", nargs="+", default=None, help="planner classes, or 'none' (default: GA, PSO, SOS)")
    learn.add_argument(
        "--algo-kwargs",
        type=yaml_mapping,
        default={},
        help="TwoStageSAC keywords over the zoo config (policy_kwargs merge key by key)",
    )
    learn.add_argument("--out", default="runs/learn", help="output folder (results/ only when asked)")
    learn.add_argument("--jobs", type=int, default=1, help="seeds trained at once, one process and one thread each")
    learn.add_argument(
        "--zero-shot",
        type=env_name,
        default=None,
        metavar="ENV",
        help="then run the trained models on ENV (e.g. RBF-EntityShift) untrained",
    )
    learn.add_argument(
        "--decoder", default="argmax", metavar="NAME",
        help="then evaluate the trained and untrained models decoded by this strategy (sb3_taskalloc.two_stage_sac."
        "decoding: argmax, sampled, preassign_search, team_search, exact_covers, exact_top, entity_value, pooled; and on "
        "--zero-shot)",
    )  # fmt: skip
    learn.add_argument(
        "--decoder-kwargs", type=yaml_mapping, default={}, metavar="YAML",
        help="settings of --decoder, e.g. '{samples: 32}'",
    )  # fmt: skip
    learn.add_argument(
        "--more-episodes", type=int, default=0, metavar="N",
        help="then evaluate the trained and untrained models and Greedy on N further held-out episodes per seed (and "
        "on --zero-shot's env), and count the seeds above Greedy over all of them",
    )  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)

    import torch as th

    th.set_num_threads(1)
    commands = {"learn": _learn, "diagnose": _diagnose, "almighty": _almighty, "table": _table}
    commands[args.command](parser, args)


def _almighty(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    from sb3_taskalloc.experiments.almighty import almighty_figure

    if min(args.seeds, args.steps, args.every) < 1:
        parser.error("--seeds, --steps and --every must be >= 1")
    writable_folder(args.out)
    print(f"wrote {almighty_figure(args.seeds, args.steps, args.every, args.out)}")


def _table(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if args.seeds < 1:
        parser.error(f"--seeds must be >= 1, got {args.seeds}")
    from sb3_taskalloc.experiments.table import TableRun

    writable_folder(args.out)
    if args.fresh:
        for name in ("cells.csv", "models", "logs"):
            path = Path(args.out) / args.env / name
            shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)
    path = TableRun(args.env, args.seeds, args.budget, args.out, args.methods).run()
    print(path.read_text())
    print(f"wrote {path}, {path.with_suffix('.csv')}")


def _check_learn(parser: argparse.ArgumentParser, args: argparse.Namespace) -> tuple[str, ...]:
    """Refuse bad ``learn`` arguments before any training; :return: the planners to run."""
    from sb3_taskalloc.common.utils import cuda_unavailable
    from sb3_taskalloc.experiments.evaluation import PLANNERS
    from sb3_taskalloc.two_stage_sac.decoding import get_decoding_strategy

    if min(args.seeds, args.eval_episodes, args.eval_every, args.jobs) < 1:
        parser.error("--seeds, --eval-episodes, --eval-every and --jobs must be >= 1")
    if min(args.select_dagger or 0, args.first_seed, args.validation_episodes) < 0:
        parser.error("--select-dagger, --first-seed and --validation-episodes must be >= 0")
    if why := cuda_unavailable(args.device):
        parser.error(why)
    if args.zero_shot and f"TaskAlloc/{args.zero_shot}-v0" not in envs.ENV_SPECS:
        parser.error(
            f"--zero-shot: unknown env {args.zero_shot!r}; choose from {sorted(envs.ENV_SPECS)} without TaskAlloc/ and -v0"
        )
    planners = PLANNERS if args.planners is None else tuple(p for p in args.planners if p != "none")
    unknown = set(planners) - set(PLANNERS)
    if unknown:
        parser.error(f"unknown planners {sorted(unknown)}; choose from {list(PLANNERS)} or none")
    try:
        get_decoding_strategy(args.decoder, **args.decoder_kwargs)
    except ValueError as error:
        parser.error(f"--decoder: {error}")
    return planners


def _learn(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    from sb3_taskalloc.experiments.learn import LearnRun

    planners = _check_learn(parser, args)
    run = LearnRun(args.env, args.seeds, args.steps, args.eval_episodes, args.eval_every, args.algo_kwargs, planners,
                   out=args.out, validation_episodes=args.validation_episodes,
                   select_dagger=args.select_dagger, dagger_imitation=args.dagger_imitation,
                   first_seed=args.first_seed, device=args.device)  # fmt: skip
    if args.steps < (0 if run.select_dagger else 1):  # 0 steps: DAgger alone, from the initial rule
        parser.error(f"--steps must be >= 1 (>= 0 with --select-dagger), got {args.steps}")
    if run.select_dagger and not run.hyperparameters.get("policy_kwargs", {}).get("preassign", True):
        parser.error("DAgger teaches the pointer of a pre-assigning policy: with preassign: false give --select-dagger 0")
    try:  # before any training
        run.check_more_episodes(args.more_episodes)
    except ValueError as error:
        parser.error(f"--more-episodes: {error}")
    writable_folder(args.out)
    path = run.run(jobs=args.jobs)
    print(path.read_text())
    print(f"wrote {path}, {path.with_suffix('.json')}, {path.with_suffix('.png')}")
    extras: list[dict[str, Any]] = []  # each on the training env, then on --zero-shot's
    if args.decoder != "argmax":
        extras.append({"decoder": args.decoder, "decoder_kwargs": args.decoder_kwargs})
    if args.more_episodes:
        extras.append({"more_episodes": args.more_episodes})
    shifts = [None, *([args.zero_shot] if args.zero_shot else [])]
    evaluations: list[tuple[str | None, dict[str, Any]]] = [(args.zero_shot, {})] if args.zero_shot else []
    evaluations += [(shift, extra) for extra in extras for shift in shifts]
    for shift, searched in evaluations:
        again = run.reevaluate(shift, **searched)
        print(again.read_text())
        print(f"wrote {again}, {again.with_suffix('.json')}")


def _diagnose(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.experiments.diagnose import diagnose, write
    from sb3_taskalloc.zoo_config import over_zoo, training_env

    if args.steps < 0 or args.episodes < 1:
        parser.error("--steps must be >= 0 and --episodes >= 1")
    if args.branches == 1 or args.branches < 0 or args.branch_stride < 1:
        parser.error("--branches must be 0 (skip) or >= 2, and --branch-stride >= 1")
    env_id = f"TaskAlloc/{args.env}-v0"
    writable_folder(args.out)
    if args.model:
        model = TwoStageSAC.load(args.model, device="cpu")
    else:
        env, kwargs = training_env(env_id, over_zoo(env_id, args.algo_kwargs), args.seed)
        model = TwoStageSAC("TAMPolicy", env, seed=args.seed, device="cpu", **kwargs)
        if args.steps:
            model.learn(args.steps, progress_bar=True)
    source = f"--model {args.model}" if args.model else f"--steps {args.steps} --seed {args.seed}"
    if args.algo_kwargs and not args.model:
        source += f" --algo-kwargs '{json.dumps(args.algo_kwargs)}'"
    command = f"python -m sb3_taskalloc.experiments diagnose --env {args.env} {source} --episodes {args.episodes}"
    command += f" --branches {args.branches} --branch-stride {args.branch_stride}"
    path = write(
        diagnose(model, env_id, args.episodes, branches=args.branches, branch_stride=args.branch_stride, progress=True),
        args.out,
        command,
    )
    print(path.read_text())
    print(f"wrote {path}, {path.with_suffix('.json')}")


if __name__ == "__main__":
    main(sys.argv[1:])
