"""Utilities shared by the algorithms."""

from __future__ import annotations

import math
import os
import tempfile
import time
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch as th


class DivergenceError(FloatingPointError):
    """Training produced a non-finite loss or parameter: the model can no longer learn (lower the learning rate)."""


def check_finite_parameters(modules: Mapping[str, th.nn.Module | None], where: str) -> None:
    """Raise :class:`DivergenceError` naming the first parameter of ``modules`` (name -> module) that holds NaN or an
    infinite value. One multi-tensor norm per module: cheap beside a gradient step.

    :param where: when it was found, for the message (e.g. the gradient step)
    """
    for name, module in modules.items():
        params: list[th.Tensor] = list(module.parameters()) if module is not None else []
        # The largest magnitude of each tensor: infinite or NaN exactly where some entry is (a 2-norm could overflow).
        if not params or bool(th.isfinite(th.stack(th._foreach_norm(params, math.inf))).all()):
            continue
        bad = next(k for k, p in module.named_parameters() if not bool(th.isfinite(p).all()))  # type: ignore[union-attr]
        raise DivergenceError(f"training diverged {where}: parameter {name}.{bad} holds NaN or infinite values")


def check_counts(counts: dict[str, Any], minimum: int = 1) -> None:
    """A clear error for the first of ``counts`` (name -> value) that is not an integer ≥ ``minimum``. A bool is refused
    though Python makes it an ``int``: ``batch_size=True`` is a mistake, not a batch of one.

    :param counts: the values to check, by the name the error gives
    :param minimum: the smallest value allowed (1: a positive integer)
    """
    what = "a positive integer" if minimum == 1 else f"an integer ≥ {minimum}"
    for name, count in counts.items():
        if isinstance(count, bool) or not (isinstance(count, int) and count >= minimum):
            raise ValueError(f"{name} must be {what}, got {count!r}")


def check_choices(choices: dict[str, tuple[Any, tuple[Any, ...]]]) -> None:
    """A clear error for the first of ``choices`` (name -> (value, allowed values)) whose value is not allowed."""
    for name, (value, allowed) in choices.items():
        if value not in allowed:
            raise ValueError(f"{name} must be {' or '.join(map(repr, allowed))}, got {value!r}")


def check_bools(flags: dict[str, Any]) -> None:
    """A clear error for the first of ``flags`` (name -> value) that is not a bool: ``"false"`` or ``"no"`` would act
    as True, and 0/1 from a YAML file are accepted as what they mean."""
    for name, flag in flags.items():
        if not isinstance(flag, bool | np.bool_) and flag not in (0, 1):
            raise ValueError(f"{name} must be True or False, got {flag!r}")


def check_finite(values: dict[str, Any], minimum: float = 0.0, inclusive: bool = False) -> None:
    """A clear error for the first of ``values`` (name -> value) that is not a finite number above ``minimum`` (or at
    least ``minimum`` with ``inclusive``). A bool is refused: ``tau=True`` is a mistake, not 1.0.

    :param values: the values to check, by the name the error gives
    :param minimum: the bound
    :param inclusive: whether ``minimum`` itself is allowed
    """
    what = "a finite number" + ("" if minimum == -math.inf else f" {'>=' if inclusive else '>'} {minimum:g}")
    for name, value in values.items():
        number = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
        if not (number and (value >= minimum if inclusive else value > minimum)):
            raise ValueError(f"{name} must be {what}, got {value!r}")


def settings_over(name: str, given: Any, defaults: dict[str, Any]) -> dict[str, Any]:
    """The settings mapping ``given`` (None: none) over ``defaults``, with a clear error for anything but a mapping of
    known keys (a ``*_kwargs`` argument: ``select_kwargs``, ``mixer_kwargs``).

    :param name: the argument's name, for the error message
    """
    if not isinstance(given, dict | None):
        raise ValueError(f"{name} must be a mapping of {sorted(defaults)}, got {given!r}")
    unknown = sorted(set(given or {}) - set(defaults))
    if unknown:
        raise ValueError(f"{name}: unknown settings {unknown}; choose from {sorted(defaults)}")
    return {**defaults, **(given or {})}


def cuda_unavailable(device: str) -> str | None:
    """Why the command-line option ``--device`` cannot be ``device`` on this machine: a message when it names CUDA and
    torch sees no CUDA device, else None (the commands refuse it before any work, each in its own way)."""
    if device == "cuda" and not th.cuda.is_available():
        return f"--device cuda: no CUDA device is available to torch {th.__version__}"
    return None


@th.no_grad()
def foreach_polyak_update(params: Iterable[th.Tensor], target_params: Iterable[th.Tensor], tau: float) -> None:
    """SB3's :func:`~stable_baselines3.common.utils.polyak_update` (θ' ← (1 − τ)·θ' + τ·θ, the same arithmetic) with
    one multi-tensor kernel per operation instead of a Python loop over the parameters."""
    params, target_params = list(params), list(target_params)
    if len(params) != len(target_params):
        raise ValueError(f"{len(params)} parameters but {len(target_params)} target parameters")
    th._foreach_mul_(target_params, 1 - tau)
    th._foreach_add_(target_params, params, alpha=tau)


def with_default_suffix(path: str | os.PathLike[str], suffix: str) -> Path:
    """``path`` with ``suffix`` (e.g. ``".zip"``) added when it has none, as SB3 names the files it saves."""
    path = Path(path)
    return path if path.suffix else path.with_suffix(suffix)


@contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """A temporary file in ``path``'s folder that replaces ``path`` (``os.replace``, atomic on POSIX) only when the
    block ends without an error: an interrupted or failed write never leaves a truncated file in place of a good one.

    :param path: the file to write (its folder is created)
    :return: the temporary path to write to (same suffix as ``path``)
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # A kill during an earlier save leaves its temporary file behind: one older than an hour is no save in progress.
    for stale in path.parent.glob(f".{path.stem}.*.tmp{path.suffix}"):
        if time.time() - stale.stat().st_mtime > 3600:
            stale.unlink(missing_ok=True)
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}")
    os.close(fd)
    tmp = Path(name)
    umask = os.umask(0)  # mkstemp creates the file 0600; the saved file gets the mode any new file would (0644 usually)
    os.umask(umask)
    tmp.chmod(0o666 & ~umask)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def writable_folder(path: str | os.PathLike[str]) -> Path:
    """``path`` created and checked for writing before any work is done, or ``SystemExit`` naming the problem: a command
    line's ``--out`` that cannot be written must not cost a run whose results it would lose at the end."""
    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as error:
        raise SystemExit(f"error: cannot write to --out {folder}: {error.strerror or error}") from None
    return folder
