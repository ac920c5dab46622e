"""Optuna samplers of TwoStageSAC hyperparameters, in rl-zoo3's signature.

``sample_two_stage_sac_params(trial, n_actions, n_envs, additional_args)`` draws the raw parameters in
well-conditioned spaces (log scales for rates and 1 − γ, powers of two for batch sizes, categorical widths) and
returns them converted into TwoStageSAC keyword arguments, exactly as rl-zoo3's own samplers do;
``convert_two_stage_sac_params`` is the converter rl-zoo3 applies to a stored trial's parameters (``--trial-id``).
Every returned value is a primitive (numbers, strings, booleans, dicts of them), so it pastes into a zoo YAML file.
"""

from __future__ import annotations

from typing import Any

import optuna

#: Raw search space (names are the trial's parameter names), shared by the sampler and the docs. Beside SAC's own
#: settings it holds the ones the learning experiment found to matter (docs/learning.md): the priors that hold each
#: actor near its rule, the actors' inverse temperatures, the decision rounds and the team search's weight.
SEARCH_SPACE = {
    "learning_rate": "log-uniform [3e-5, 3e-3]",
    "one_minus_gamma": "log-uniform [1e-3, 0.1] (γ = 1 − value)",
    "tau": "log-uniform [1e-3, 0.05]",
    "batch_size_pow": "int [4, 7] (batch 16 … 128)",
    "select_batch_size_pow": "int [2, 5] (select rows 4 … 32)",
    "learning_starts": "{0, 100, 500, 1000}",
    "target_entropy_ratio": "uniform [0.05, 0.6]",
    "hidden_dim": "{32, 64, 128}",
    "n_attention_layers": "{0, 1}",
    "prior_coef": "log-uniform [0.01, 10] (β, the pre-assign actor's prior term)",
    "select_prior_coef": "log-uniform [0.3, 30] (β_s, the pointer's prior term)",
    "logit_scale": "log-uniform [10, 1000] (κ, the pre-assign actor's inverse temperature)",
    "select_logit_scale": "log-uniform [1, 100] (κ_s, the pointer's)",
    "rounds": "{1, 2, 4} (decision rounds)",
    "select_search_coef": "{0, 10, 30} (λ_p, the team search's weight; 32 decodes when > 0)",
}

#: Trial parameters that are keywords of ``policy_kwargs`` and of ``select_kwargs`` (by their keyword).
POLICY_PARAMS = ("hidden_dim", "n_attention_layers", "logit_scale", "select_logit_scale", "rounds")
SELECT_PARAMS = {"select_prior_coef": "prior_coef", "select_search_coef": "search_coef"}


def convert_two_stage_sac_params(sampled_params: dict[str, Any]) -> dict[str, Any]:
    """Turn raw trial parameters (see :data:`SEARCH_SPACE`) into TwoStageSAC keyword arguments.

    :param sampled_params: ``trial.params`` of a TwoStageSAC trial
    :return: keyword arguments (``policy_kwargs`` included) with primitive values
    """
    params = dict(sampled_params)
    hyperparams: dict[str, Any] = {}
    if "one_minus_gamma" in params:
        hyperparams["gamma"] = 1.0 - params.pop("one_minus_gamma")
    if "batch_size_pow" in params:
        hyperparams["batch_size"] = 2 ** int(params.pop("batch_size_pow"))
    select_kwargs = {keyword: params.pop(name) for name, keyword in SELECT_PARAMS.items() if name in params}
    if "select_batch_size_pow" in params:
        select_kwargs["batch_size"] = 2 ** int(params.pop("select_batch_size_pow"))
    if select_kwargs.get("search_coef"):
        select_kwargs["search_samples"] = 32
    if select_kwargs:
        hyperparams["select_kwargs"] = select_kwargs
    policy_kwargs = {key: params.pop(key) for key in POLICY_PARAMS if key in params}
    if policy_kwargs:
        hyperparams["policy_kwargs"] = policy_kwargs
    hyperparams.update(params)
    return hyperparams


def sample_two_stage_sac_params(
    trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict[str, Any]
) -> dict[str, Any]:
    """Sample TwoStageSAC hyperparameters (rl-zoo3 sampler signature).

    :param trial: the Optuna trial
    :param n_actions: size of the action vector (entities); unused, part of rl-zoo3's signature
    :param n_envs: number of parallel envs; unused (one gradient step per env step is kept)
    :param additional_args: rl-zoo3's extra arguments (HER settings); unused
    :return: TwoStageSAC keyword arguments
    """
    sampled = {
        "learning_rate": trial.suggest_float("learning_rate", 3e-5, 3e-3, log=True),
        "one_minus_gamma": trial.suggest_float("one_minus_gamma", 1e-3, 0.1, log=True),
        "tau": trial.suggest_float("tau", 1e-3, 0.05, log=True),
        "batch_size_pow": trial.suggest_int("batch_size_pow", 4, 7),
        "select_batch_size_pow": trial.suggest_int("select_batch_size_pow", 2, 5),
        "learning_starts": trial.suggest_categorical("learning_starts", [0, 100, 500, 1000]),
        "target_entropy_ratio": trial.suggest_float("target_entropy_ratio", 0.05, 0.6),
        "hidden_dim": trial.suggest_categorical("hidden_dim", [32, 64, 128]),
        "n_attention_layers": trial.suggest_categorical("n_attention_layers", [0, 1]),
        "prior_coef": trial.suggest_float("prior_coef", 0.01, 10.0, log=True),
        "select_prior_coef": trial.suggest_float("select_prior_coef", 0.3, 30.0, log=True),
        "logit_scale": trial.suggest_float("logit_scale", 10.0, 1000.0, log=True),
        "select_logit_scale": trial.suggest_float("select_logit_scale", 1.0, 100.0, log=True),
        "rounds": trial.suggest_categorical("rounds", [1, 2, 4]),
        "select_search_coef": trial.suggest_categorical("select_search_coef", [0.0, 10.0, 30.0]),
    }
    hyperparams = convert_two_stage_sac_params(sampled)
    trial.set_user_attr("gamma", hyperparams["gamma"])
    trial.set_user_attr("batch_size", hyperparams["batch_size"])
    return hyperparams


class TrialSeededTPESampler(optuna.samplers.TPESampler):
    """TPE whose random state is set, before each trial samples, from the study's ``seed`` and the trial's number.

    The trial number is handed out by the storage, one per trial across every worker, so workers that join a study
    at the same moment still propose different parameters, and a study run again on the same state proposes the same
    ones (a seed taken when a worker joins gives two workers starting together the same proposals)."""

    def __init__(self, seed: int, **kwargs: Any) -> None:
        super().__init__(seed=seed, **kwargs)
        self.study_seed = seed

    def before_trial(self, study: optuna.Study, trial: optuna.trial.FrozenTrial) -> None:
        seed = (self.study_seed * 1_000_003 + trial.number) % 2**32
        # TPE's own generator and that of its random start-up sampler (Optuna keeps both as LazyRandomState)
        self._rng.rng.seed(seed)
        self._random_sampler._rng.rng.seed(seed)
        super().before_trial(study, trial)
