"""The rl-zoo3 configs shipped with the package (``zoo_configs/*.yml``, package data) and what reads them: an env's
block as TwoStageSAC keywords, its DAgger callback, and the training env of ``n_envs`` copies. The zoo launcher, the
experiments and :meth:`TwoStageSAC.from_zoo <sb3_taskalloc.TwoStageSAC.from_zoo>` read the same blocks."""

from __future__ import annotations

import copy
import functools
from importlib import resources
from pathlib import Path
from typing import Any


def config_path(name: str) -> Path:
    """The shipped config ``name`` (``"two_stage_sac.yml"``, ``"maskable_ppo.yml"``, ``"ddpg.yml"``), in the source tree
    or in an installed wheel alike."""
    return Path(str(resources.files("zoo_configs") / name))


#: rl-zoo3's import path of the one callback of a zoo block that the experiments run: the DAgger of the pointer, which
#: ``learn`` runs as its DAgger phase (``--select-dagger``) and the table after training its columns.
DAGGER_CALLBACK = "sb3_taskalloc.two_stage_sac.callbacks.SelectDAggerCallback"


#: Keys of a zoo block that are rl-zoo3's, not TwoStageSAC keywords.
ZOO_ONLY = ("policy", "n_timesteps", "callback")


@functools.lru_cache(maxsize=16)
def _parsed(text: str) -> dict[str, Any]:
    """A config file's blocks, parsed once per text (a parse takes about 20 ms, and an experiment reads its env's block
    for every model it builds)."""
    import yaml

    return yaml.safe_load(text) or {}


def _zoo_block(env_id: str, path: str | Path | None) -> tuple[Path, dict[str, Any]]:
    """The config file read and ``env_id``'s block in it (a copy the caller may change); a clear error when either is
    missing (a silent ``{}`` would train another configuration)."""
    path = Path(path) if path else config_path("two_stage_sac.yml")
    if not path.is_file():
        raise FileNotFoundError(f"no zoo config at {path}")
    blocks = _parsed(path.read_text())
    if env_id not in blocks:
        known = sorted(k for k in blocks if k != "default")
        raise ValueError(f"{path} has no block for {env_id!r}; it has {known}")
    return path, copy.deepcopy(blocks[env_id])


def zoo_hyperparameters(env_id: str, path: str | Path | None = None) -> dict[str, Any]:
    """TwoStageSAC keywords of ``env_id`` from ``zoo_configs/two_stage_sac.yml`` (the same values the zoo trains with;
    ``policy``, ``n_timesteps`` and ``callback`` left out). The block's
    callbacks are :func:`zoo_dagger`'s, which refuses any the experiments do not run (``learn`` and the table run its
    DAgger; ``bench``, ``diagnose`` and the demo measure the TwoStageSAC steps alone)."""
    path, block = _zoo_block(env_id, path)
    _dagger_of(block, f"{path}: the block of {env_id}")
    return {k: v for k, v in block.items() if k not in ZOO_ONLY}


def zoo_dagger(env_id: str, path: str | Path | None = None) -> dict[str, Any]:
    """Keywords of the :class:`~sb3_taskalloc.SelectDAggerCallback` in ``env_id``'s ``callback`` entry of
    ``zoo_configs/two_stage_sac.yml`` (rl-zoo3's key; ``python -m sb3_taskalloc.zoo`` runs it when training ends), with
    the callback's defaults filled in and ``seed`` left out; ``{}`` when the block has none. The experiments run it as
    their DAgger phase after the training steps. Any other callback, a second DAgger entry or keywords the callback
    refuses raise a ValueError naming the file and the block: an entry the experiments dropped would report a schedule
    the zoo does not train."""
    path, block = _zoo_block(env_id, path)
    return _dagger_of(block, f"{path}: the block of {env_id}")


def _dagger_of(block: dict[str, Any], where: str) -> dict[str, Any]:
    """:func:`zoo_dagger` of a block already read (``where`` names it in the errors)."""
    entries = block.get("callback") or []
    dagger: dict[str, Any] = {}
    for entry in entries if isinstance(entries, list) else [entries]:
        name, kwargs = next(iter(entry.items())) if isinstance(entry, dict) and len(entry) == 1 else (entry, {})
        if name != DAGGER_CALLBACK:
            raise ValueError(
                f"{where} has the callback {name!r}, which the experiments do not run (they run {DAGGER_CALLBACK} as "
                "their DAgger phase); train with python -m sb3_taskalloc.zoo to run it"
            )
        if dagger:
            raise ValueError(f"{where} has {DAGGER_CALLBACK} twice")
        from sb3_taskalloc.two_stage_sac.callbacks import SelectDAggerCallback

        try:
            callback = SelectDAggerCallback(**(kwargs or {}))
        except (TypeError, ValueError) as error:
            raise ValueError(f"{where}: {DAGGER_CALLBACK}: {error}") from error
        if callback.seed is not None:
            raise ValueError(f"{where}: {DAGGER_CALLBACK} sets a seed; the experiments seed each training seed's rollouts")
        # The observation's costs (teacher None) are left out, so the digests of runs before the keyword stay valid.
        dagger = {k: v for k, v in callback.kwargs.items() if not (k == "teacher" and v is None)}
    return dagger


def over_zoo(env_id: str, overrides: dict[str, Any]) -> dict[str, Any]:
    """The env's zoo hyperparameters (:func:`zoo_hyperparameters`) with ``overrides`` on top. The settings mappings
    (``policy_kwargs``, ``select_kwargs``) merge key by key: overriding one policy keyword (``{policy_kwargs:
    {hidden_dim: 128}}``) keeps the block's others (its ``rounds``, its rule), as overriding one algorithm keyword keeps
    the rest of the block."""
    return merge_settings(zoo_hyperparameters(env_id), overrides)


def merge_settings(base: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """TwoStageSAC keywords ``overrides`` over ``base``; the settings mappings (``policy_kwargs``, ``select_kwargs``)
    merge key by key."""
    merged = {**base, **overrides}
    for key in ("policy_kwargs", "select_kwargs"):
        if isinstance(base.get(key), dict) and isinstance(overrides.get(key), dict):
            merged[key] = {**base[key], **overrides[key]}
    return merged


def training_env(
    env_id: str, hyperparameters: dict[str, Any], seed: int, env_kwargs: dict[str, Any] | None = None
) -> tuple[Any, dict[str, Any]]:
    """The env TwoStageSAC trains on under zoo-style ``hyperparameters``, and the keywords left for TwoStageSAC: with
    ``n_envs`` > 1 (rl-zoo3's key for vectorised collection) a VecEnv of that many copies seeded from ``seed``, else
    the env id itself (or the env made with ``env_kwargs``)."""
    kwargs = dict(hyperparameters)
    n_envs = int(kwargs.pop("n_envs", 1))
    if n_envs == 1:
        if env_kwargs:
            import gymnasium as gym

            return gym.make(env_id, **env_kwargs), kwargs
        return env_id, kwargs
    from stable_baselines3.common.env_util import make_vec_env

    return make_vec_env(env_id, n_envs=n_envs, seed=seed, env_kwargs=env_kwargs), kwargs


def zoo_block(env_id: str) -> dict[str, Any]:
    """``env_id``'s whole block of the shipped ``two_stage_sac.yml`` (rl-zoo3's keys included), as rl-zoo3 reads it."""
    return _zoo_block(env_id, None)[1]


def from_zoo(cls: Any, env_id: str, seed: int | None = None, **overrides: Any) -> Any:
    """``cls`` (TwoStageSAC) built with ``env_id``'s block of the shipped ``two_stage_sac.yml``: its keywords with
    ``overrides`` on top (the settings mappings merge key by key), on ``n_envs`` copies of the env, with the block's
    budget as ``learn()``'s default and its DAgger callback run when each ``learn`` ends (:attr:`zoo_callbacks`).

    :param env_id: a ``TaskAlloc`` id (importing ``sb3_taskalloc`` registers them)
    :param seed: the model's seed (and the envs')
    :param overrides: TwoStageSAC keywords over the block's, ``n_envs`` and ``n_timesteps`` included
    """
    from sb3_taskalloc.two_stage_sac.callbacks import SelectDAggerCallback

    path, block = _zoo_block(env_id, None)  # read once: the keywords, the budget and the DAgger all come from it
    dagger = _dagger_of(block, f"{path}: the block of {env_id}")
    n_timesteps = int(overrides.pop("n_timesteps", block.get("n_timesteps", 0)))
    hyperparameters = merge_settings({k: v for k, v in block.items() if k not in ZOO_ONLY}, overrides)
    env, kwargs = training_env(env_id, hyperparameters, 0 if seed is None else seed)
    model = cls("TAMPolicy", env, seed=seed, **kwargs)
    model.zoo_n_timesteps = n_timesteps or None
    model.zoo_callbacks = [SelectDAggerCallback(**dagger)] if dagger else []
    return model
