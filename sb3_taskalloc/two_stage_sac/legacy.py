"""Models saved by sb3_taskalloc before the options of ``docs/learning.md`` left the library (commit 632165d and
earlier) load unchanged: their settings are converted to today's, with a warning for what no longer exists.

- The decision-time searches that were ``TAMPolicy`` keywords become the model's decoding strategy
  (:mod:`.decoding`): ``decision_samples`` → ``"preassign_search"``, ``select_decision_samples`` and
  ``select_decision_exact`` → ``"team_search"``, ``decision_exact_top`` → ``"exact_top"``.
- The AMIX settings ``monotonic_mixer``, ``hyper_bias`` and ``team_value`` move into ``mixer_kwargs``; the select
  stage's ``select_*`` settings of the algorithm into ``select_kwargs``.
- The future critic (``mixer="future"``, removed after :data:`FUTURE_CRITIC_COMMIT`) has the parameters of a
  monotonic AMIX critic without a team value, and loads as one: its pre-assign actor was held, so no decision read the
  critic, and the model decides as it did.
- Training terms that were removed (their verdicts are in ``docs/learning.md``) are dropped: a loaded model decides as
  it did, and further training runs without them. Pointer architectures that were removed cannot load (their weights
  have no place in today's networks); the error names the commit that still has them.
"""

from __future__ import annotations

import pathlib
import warnings
import zipfile
from typing import Any

from stable_baselines3.common.save_util import json_to_data

from sb3_taskalloc.common.utils import with_default_suffix
from sb3_taskalloc.two_stage_sac.decoding import Decoder, get_decoding_strategy
from sb3_taskalloc.two_stage_sac.policies import TAMPolicy

#: The last commit whose library held the removed options.
LAST_COMMIT = "632165d"

#: Removed training terms of TwoStageSAC (attribute -> the value at which it did nothing).
REMOVED_TERMS: dict[str, Any] = {
    "actor_warmup": 0,
    "profit_coef": 0.0,
    "search_coef": 0.0,
    "select_search_method": "sample",
    "counterfactual_rate": 0.0,
}
#: Their companions, dropped with them.
REMOVED_COMPANIONS = (
    "profit_entities",
    "profit_batch_size",
    "search_samples",
    "search_temperature",
    "search_batch_size",
    "select_search_batch_size",
    "counterfactual_batch_size",
    "counterfactual_coef",
    "counterfactual_buffer",
    "_branched",
)
#: The last commit whose library held the future critic (``mixer="future"``) and the ``value_top`` decoder.
FUTURE_CRITIC_COMMIT = "986c6cf"
#: Removed pointer architectures (policy keyword -> its value when off).
REMOVED_ARCHITECTURES: dict[str, Any] = {"select_pair_hidden": 0, "select_scarcity": False}
#: TAMPolicy keywords that moved into ``mixer_kwargs`` (old name -> new key).
MIXER_KEYS = {"monotonic_mixer": "monotonic", "hyper_bias": "hyper_bias", "team_value": "team_value"}
#: TwoStageSAC attributes that moved into ``select_kwargs`` (old name -> new key).
SELECT_KEYS = {
    "select_ent_coef": "ent_coef",
    "select_prior_coef": "prior_coef",
    "select_batch_size": "batch_size",
    "select_search_coef": "search_coef",
    "select_search_samples": "search_samples",
    "select_search_temperature": "search_temperature",
}
_DECODER_KEYS = (
    "decision_samples",
    "decision_temperature",
    "select_decision_samples",
    "select_decision_temperature",
    "select_decision_exact",
    "decision_exact_top",
)


def check_policy_kwargs(policy_class: type[Any], policy_kwargs: dict[str, Any]) -> None:
    """A clear error for a ``policy_kwargs`` key that ``policy_class`` does not take, or a removed mixer, naming where a
    moved or removed option went."""
    import inspect

    if policy_kwargs.get("mixer") == "future":
        raise ValueError(
            "mixer='future' (the critic Q = P + F read by the value_top decoder) was removed: a uniform surcharge on "
            "the pair costs decided as well, set_decoder('exact_top', top=2, surcharge=0.08), and learned per-robot "
            "values better, set_decoder(recommended_decoder('TaskAlloc/RBF-v0')) (docs/learning.md); the "
            f"last commit with it is {FUTURE_CRITIC_COMMIT}. A model saved with it still loads"
        )
    accepted = set(inspect.signature(policy_class.__init__).parameters)
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in inspect.signature(policy_class.__init__).parameters.values()):
        return
    for key in policy_kwargs:
        if key in accepted:
            continue
        if key in _DECODER_KEYS:
            raise ValueError(
                f"policy_kwargs[{key!r}]: how a trained model decides is its decoding strategy now, not a policy keyword: "
                "model.set_decoder(name, **settings) (sb3_taskalloc.two_stage_sac.decoding)"
            )
        if key in MIXER_KEYS:
            raise ValueError(f"policy_kwargs[{key!r}] is mixer_kwargs[{MIXER_KEYS[key]!r}] now")
        if key in REMOVED_ARCHITECTURES:
            raise ValueError(f"policy_kwargs[{key!r}] was removed (measured as not helping, docs/learning.md)")
        raise ValueError(
            f"policy_kwargs: {policy_class.__name__} takes no keyword {key!r}; it takes {sorted(accepted - {'self'})}"
        )


def saved_data(path: str | pathlib.Path) -> dict[str, Any] | None:
    """The ``data`` of a saved model (its settings, without the weights), or None where there is no such file."""
    found = next((p for p in (pathlib.Path(path), with_default_suffix(path, ".zip")) if p.is_file()), None)
    if found is None or not zipfile.is_zipfile(found):
        return None
    with zipfile.ZipFile(found) as archive:
        if "data" not in archive.namelist():
            return None
        return json_to_data(archive.read("data").decode())


def decoder_of(policy_kwargs: dict[str, Any]) -> Decoder | None:
    """The decoding strategy of an old model's decision-time keywords (popped from ``policy_kwargs``), or None."""
    old = {k: policy_kwargs.pop(k) for k in _DECODER_KEYS if k in policy_kwargs}
    if old.get("decision_exact_top", 0):
        return get_decoding_strategy("exact_top", top=old["decision_exact_top"])
    if old.get("decision_samples", 1) > 1:
        return get_decoding_strategy(
            "preassign_search", samples=old["decision_samples"], temperature=old.get("decision_temperature", 2.0)
        )
    if old.get("select_decision_samples", 1) > 1 or old.get("select_decision_exact", False):
        return get_decoding_strategy(
            "team_search",
            samples=old.get("select_decision_samples", 1),
            temperature=old.get("select_decision_temperature", 1.0),
            exact=bool(old.get("select_decision_exact", False)),
        )
    return None


def convert(data: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any], Decoder | None]:
    """What an old model's ``data`` needs to load today.

    :return: the replaced items of ``data`` (``custom_objects`` of SB3's ``load``), the attributes to add (its
        ``**kwargs``; the removed settings' attributes are dropped after loading, :func:`finish`) and the decoding
        strategy of its decision-time keywords (None: the argmax)
    """
    policy_class = data.get("policy_class")
    if isinstance(policy_class, type) and not issubclass(policy_class, TAMPolicy):
        raise ValueError(
            f"this file holds a model with a {policy_class.__name__} policy, not a TwoStageSAC model: load it with its "
            "own algorithm class"
        )
    policy_kwargs = dict(data.get("policy_kwargs") or {})
    removed = {k: policy_kwargs[k] for k in REMOVED_ARCHITECTURES if k in policy_kwargs}
    if any(v != REMOVED_ARCHITECTURES[k] for k, v in removed.items()):
        raise ValueError(
            f"this model's pointer was built with {removed}, an architecture measured as not helping and removed from "
            f"sb3_taskalloc (docs/learning.md); load it with the library at commit {LAST_COMMIT}"
        )
    for key in removed:
        del policy_kwargs[key]
    decoder = decoder_of(policy_kwargs)
    if policy_kwargs.get("mixer") == "future":
        policy_kwargs["mixer"] = "amix"
        policy_kwargs["mixer_kwargs"] = {**policy_kwargs.get("mixer_kwargs", {}), "monotonic": True, "team_value": False}
        warnings.warn(
            "this model was trained with the future critic (mixer='future'), removed from sb3_taskalloc: its critic "
            "loads as an AMIX critic, which no decision reads with its actor held, so it decides as before; decode it "
            "with set_decoder('exact_top', top=2, surcharge=0.08) where it used value_top, or with its env's "
            "recommended_decoder(env_id), which does better on RBF (docs/learning.md)",
            stacklevel=3,
        )
    mixer = {new: policy_kwargs.pop(old) for old, new in MIXER_KEYS.items() if old in policy_kwargs}
    if mixer:
        policy_kwargs["mixer_kwargs"] = {**policy_kwargs.get("mixer_kwargs", {}), **mixer}
    custom: dict[str, Any] = {"policy_kwargs": policy_kwargs} if policy_kwargs != (data.get("policy_kwargs") or {}) else {}
    attributes: dict[str, Any] = {}
    if "select_kwargs" not in data and any(k in data for k in SELECT_KEYS):
        attributes["select_kwargs"] = {new: data[old] for old, new in SELECT_KEYS.items() if old in data}
    dropped = sorted(k for k, off in REMOVED_TERMS.items() if k in data and data[k] != off)
    if dropped:
        warnings.warn(
            f"this model was trained with {dropped}, training terms removed from sb3_taskalloc (docs/learning.md): it "
            "decides as before, and further training runs without them",
            stacklevel=3,
        )
    if decoder is not None:
        warnings.warn(
            f"this model was saved with a decision-time search among its policy keywords; it is now its decoding "
            f"strategy {decoder!r} (model.set_decoder)",
            stacklevel=3,
        )
    return custom, attributes, decoder


def load_arguments(
    path: str | pathlib.Path, custom_objects: dict[str, Any] | None, kwargs: dict[str, Any]
) -> tuple[dict[str, Any] | None, dict[str, Any], Decoder | None]:
    """SB3's ``load`` arguments for the model at ``path``, its old settings converted (:func:`convert`): the
    ``custom_objects`` and ``**kwargs`` to pass, and the decoding strategy to set after loading (None: the argmax)."""
    data = saved_data(path)
    if data is None:
        return custom_objects, kwargs, None
    converted, attributes, decoder = convert(data)
    return {**converted, **(custom_objects or {})}, {**attributes, **kwargs}, decoder


def finish(model: Any, decoder: Decoder | None) -> None:
    """After SB3's ``load``: drop the removed settings' attributes and set the old model's decoding strategy."""
    for key in (*REMOVED_TERMS, *REMOVED_COMPANIONS, *SELECT_KEYS):
        model.__dict__.pop(key, None)
    if decoder is not None:
        model.policy.decoder = decoder
