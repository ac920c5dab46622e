"""rl-zoo3 launcher: ``python -m sb3_taskalloc.zoo {train,enjoy} [rl-zoo3 arguments]``.

Registers ``two_stage_sac`` (:class:`~sb3_taskalloc.TwoStageSAC`) and ``maskable_ppo`` (sb3-contrib's MaskablePPO,
the naive RL baseline) into rl-zoo3 the documented way, by adding them to its ``ALGOS`` dict and, for
``-optimize``, to its ``HYPERPARAMS_SAMPLER`` / ``HYPERPARAMS_CONVERTER`` registries; then it runs rl-zoo3's own
``train()`` or ``enjoy()`` with the remaining arguments. ``--gym-packages envs`` is added when absent, so the
``TaskAlloc/*`` ids are registered in rl-zoo3's process (and in its subprocess envs)::

    python -m sb3_taskalloc.zoo train --algo two_stage_sac --env TaskAlloc/RBF-v0  # the shipped zoo_configs/two_stage_sac.yml
    python -m sb3_taskalloc.zoo enjoy --algo two_stage_sac --env TaskAlloc/RBF-v0 -f logs --exp-id 1 -n 300

rl-zoo3 is an optional extra (``pip install -e ".[zoo]"``); importing :mod:`sb3_taskalloc` never imports it.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from sb3_taskalloc.two_stage_sac import TwoStageSAC

COMMANDS = ("train", "enjoy")


class EnjoyTwoStageSAC(TwoStageSAC):
    """What rl-zoo3's ``enjoy`` loads for ``two_stage_sac``: a :class:`TwoStageSAC` with a one-transition replay
    buffer (``enjoy`` shrinks the buffers of the off-policy algorithms it knows, not of registered ones)."""

    @classmethod
    def load(cls, path: Any, *args: Any, **kwargs: Any) -> Any:  # type: ignore[override]
        kwargs.setdefault("buffer_size", 1)
        return TwoStageSAC.load(path, *args, **kwargs)


def register(command: str = "train") -> None:
    """Add ``two_stage_sac`` and ``maskable_ppo`` to rl-zoo3's algorithm and sampler registries.

    :param command: ``"train"`` or ``"enjoy"`` (the latter loads TwoStageSAC models with a minimal replay buffer)
    """
    try:
        from rl_zoo3 import hyperparams_opt
        from rl_zoo3 import utils as zoo_utils
    except ImportError as error:
        raise ImportError('rl-zoo3 is an optional extra: pip install -e ".[zoo]"') from error
    from sb3_contrib import MaskablePPO

    from tuning.samplers import convert_two_stage_sac_params, sample_two_stage_sac_params

    zoo_utils.ALGOS["two_stage_sac"] = EnjoyTwoStageSAC if command == "enjoy" else TwoStageSAC
    zoo_utils.ALGOS["maskable_ppo"] = MaskablePPO
    hyperparams_opt.HYPERPARAMS_SAMPLER["two_stage_sac"] = sample_two_stage_sac_params
    hyperparams_opt.HYPERPARAMS_CONVERTER["two_stage_sac"] = convert_two_stage_sac_params
    hyperparams_opt.HYPERPARAMS_SAMPLER["maskable_ppo"] = hyperparams_opt.sample_ppo_params
    hyperparams_opt.HYPERPARAMS_CONVERTER["maskable_ppo"] = hyperparams_opt.convert_onpolicy_params


def default_config(args: list[str]) -> Path:
    """The shipped config of the ``--algo`` in rl-zoo3's arguments ``args`` (``zoo_configs/<algo>.yml``): without it
    rl-zoo3 would look in its own folder, which knows none of the TaskAlloc ids."""
    from sb3_taskalloc.zoo_config import config_path

    algo = args[args.index("--algo") + 1] if "--algo" in args[:-1] else "two_stage_sac"
    path = config_path(f"{algo}.yml")
    if not path.is_file():
        raise SystemExit(f"no shipped zoo config for --algo {algo}: give --conf-file")
    return path


def _value(args: list[str], *names: str) -> str | None:
    """The value after the first of ``names`` in rl-zoo3's arguments ``args``, or None."""
    return next((args[i + 1] for i, a in enumerate(args[:-1]) if a in names), None)


def check_block(args: list[str]) -> None:
    """A clear error, before rl-zoo3 starts, for a YAML config whose ``--env`` block lacks the keys rl-zoo3 needs
    (``policy``; ``n_timesteps`` unless ``-n`` gives it): rl-zoo3 stops at them with a bare ``KeyError`` or a
    ``TypeError`` about a missing positional argument."""
    import yaml

    conf, env = _value(args, "--conf-file", "-conf"), _value(args, "--env")
    if conf is None or env is None or not conf.endswith((".yml", ".yaml")) or not Path(conf).is_file():
        return  # rl-zoo3's own messages cover these (a missing file, a Python config)
    try:
        with open(conf) as stream:  # the stream names the file in YAML's message
            blocks = yaml.safe_load(stream) or {}
    except yaml.YAMLError as error:
        raise SystemExit(f"error: {conf} is not valid YAML: {error}") from None
    block = blocks.get(env) if isinstance(blocks, dict) else None
    if not isinstance(block, dict):
        return  # rl-zoo3 names a missing block
    n_given = int(_value(args, "-n", "--n-timesteps") or -1) > 0
    missing = [key for key in ("policy", "n_timesteps") if key not in block and not (key == "n_timesteps" and n_given)]
    if missing:
        raise SystemExit(
            f"error: {conf}: the block of {env} has no {' or '.join(missing)}, which rl-zoo3 needs "
            "(policy: TAMPolicy; n_timesteps: N, or -n N on the command line)"
        )


def main(argv: list[str] | None = None) -> None:
    """Run rl-zoo3's ``train`` or ``enjoy`` with the project's algorithms registered.

    :param argv: ``[command, *rl-zoo3 arguments]`` (default: ``sys.argv[1:]``)
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in COMMANDS:
        print(__doc__)
        raise SystemExit(f"usage: python -m sb3_taskalloc.zoo {{{','.join(COMMANDS)}}} [rl-zoo3 arguments]")
    command, rest = argv[0], argv[1:]
    if "--gym-packages" not in rest:
        rest += ["--gym-packages", "envs"]
    if command == "train" and not {"--conf-file", "-conf"} & set(rest):
        rest += ["--conf-file", str(default_config(rest))]
    if command == "train":
        check_block(rest)
    register(command)
    if command == "train":
        from rl_zoo3.train import train as run
    else:
        from rl_zoo3.enjoy import enjoy as run
    sys.argv = [f"rl_zoo3 {command}", *rest]
    run()


if __name__ == "__main__":
    main()
