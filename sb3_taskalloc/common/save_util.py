"""Saving that loses nothing: SB3's files written atomically, and saved models checked before they are loaded."""

from __future__ import annotations

import io
import json
import pathlib
import zipfile
from collections.abc import Iterable, Sequence

from sb3_taskalloc.common.utils import atomic_path, with_default_suffix


class AtomicSaveMixin:
    """For an SB3 algorithm: :meth:`save` and :meth:`save_replay_buffer` write to a temporary file beside ``path`` and
    move it over ``path`` when complete, so a save that fails midway (disk full, a kill) leaves the previous file intact.
    Streams are written directly."""

    def save(
        self,
        path: str | pathlib.Path | io.BufferedIOBase,
        exclude: Iterable[str] | None = None,
        include: Iterable[str] | None = None,
    ) -> None:
        if isinstance(path, io.BufferedIOBase):
            return super().save(path, exclude, include)  # type: ignore[misc]
        with atomic_path(with_default_suffix(path, ".zip")) as tmp:
            super().save(tmp, exclude, include)  # type: ignore[misc]

    def save_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase) -> None:
        if isinstance(path, io.BufferedIOBase):
            return super().save_replay_buffer(path)  # type: ignore[misc]
        with atomic_path(with_default_suffix(path, ".pkl")) as tmp:
            super().save_replay_buffer(tmp)  # type: ignore[misc]


def check_saved_model(path: str | pathlib.Path, required: Sequence[str]) -> None:
    """Raise a clear error when ``path`` (or ``path.zip``) exists but is not a complete SB3 save holding ``required``.

    :param required: archive members the model needs (``"data"``, ``"policy.pth"``, ...)
    """
    found = _saved_file(path)
    if found is None:
        raise FileNotFoundError(f"no saved model at {path}" + ("" if str(path).endswith(".zip") else " (nor .zip)"))
    if not zipfile.is_zipfile(found):
        raise ValueError(f"{found} is not a saved model (not a zip file: truncated, or another kind of file)")
    with zipfile.ZipFile(found) as archive:
        missing = sorted(set(required) - set(archive.namelist()))
        if missing:
            raise ValueError(f"{found} is not a complete saved model: it has no {', '.join(missing)}")
        if "data" in required:
            try:
                json.loads(archive.read("data"))
            except (ValueError, zipfile.BadZipFile) as error:  # a cut or edited member: SB3 would raise a bare JSON error
                raise ValueError(f"{found} has a damaged 'data' member (the model's settings): {error}") from error


def saved_members(path: str | pathlib.Path) -> list[str]:
    """The members of the saved model at ``path`` (or ``path.zip``; checked by :func:`check_saved_model`), for messages
    about what a save lacks."""
    found = _saved_file(path)
    assert found is not None
    with zipfile.ZipFile(found) as archive:
        return archive.namelist()


def _saved_file(path: str | pathlib.Path) -> pathlib.Path | None:
    """The file SB3's ``load`` reads for ``path``: ``path`` itself, else ``path.zip``; None when neither exists."""
    return next((p for p in (pathlib.Path(path), with_default_suffix(path, ".zip")) if p.is_file()), None)
