"""Decoding strategies by name: each equals the constructor option it replaces on a model saved before the change, and
a model saved with those options loads with its search as its decoder."""

from __future__ import annotations

import itertools
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.save_util import load_from_zip_file

import envs  # noqa: F401  (registers the TaskAlloc ids)
from sb3_taskalloc import TwoStageSAC
from sb3_taskalloc.two_stage_sac import search
from sb3_taskalloc.two_stage_sac.decoding import (
    DECODERS,
    Decoder,
    get_decoding_strategy,
    recommended_decoder,
    register_decoder,
)
from sb3_taskalloc.two_stage_sac.settings import RECOMMENDED_DECODERS

DATA = Path(__file__).parent / "data"
#: Made by ``tests/data/make_legacy_fixtures.py`` at commit 632165d, with each option set as a TAMPolicy attribute.
LEGACY_MODEL = DATA / "legacy_rbf_decision_samples4.zip"
LEGACY_DECISIONS = DATA / "legacy_decisions.npz"

#: fixture name -> (strategy, settings): the strategy that replaces each old option. The fixtures' sampled teams
#: (``team_search``) and sampled decisions (``sampled``) are not compared: the pointer's samples draw one uniform per
#: entity since the team search was made cheaper, a different stream from the one they were made with.
EQUIVALENT = {
    "argmax": ("argmax", {}),
    "preassign_search": ("preassign_search", {"samples": 8, "temperature": 2.0}),
    "exact_covers": ("exact_covers", {}),
    "exact_top1": ("exact_top", {"top": 1}),
    "exact_top2": ("exact_top", {"top": 2}),
}


@pytest.fixture(scope="module")
def legacy() -> tuple[TwoStageSAC, dict[str, np.ndarray]]:
    with pytest.warns(UserWarning, match="decoding strategy"):
        model = TwoStageSAC.load(LEGACY_MODEL, device="cpu")
    saved = dict(np.load(LEGACY_DECISIONS))
    return model, saved


def _obs(saved: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: v for k, v in saved.items() if k == "action_mask" or not k.startswith("action_")}


def test_old_model_loads_with_its_search_as_its_decoder(legacy):
    """The model was saved with ``decision_samples=4`` among its policy keywords: it loads with the pre-assignment
    search of 4 as its decoder, its other keywords converted, and no removed keyword left in its settings."""
    model, _ = legacy
    assert model.policy.decoder.name == "preassign_search" and model.policy.decoder.samples == 4
    assert model.policy_kwargs == {"rounds": 2, "hidden_dim": 16}
    assert model.select_kwargs["batch_size"] == 16 and model.select_kwargs["prior_coef"] == 3.0
    params = model.policy._get_constructor_parameters()
    assert not {"decision_samples", "select_scarcity", "select_pair_hidden"} & set(params)
    assert not hasattr(model, "counterfactual_rate") and not hasattr(model, "select_batch_size")
    data, _, _ = load_from_zip_file(LEGACY_MODEL, device="cpu")
    assert data["policy_kwargs"]["decision_samples"] == 4  # the file itself is untouched


@pytest.mark.parametrize("name", list(EQUIVALENT))
def test_each_strategy_equals_the_option_it_replaces(legacy, name, monkeypatch):
    model, saved = legacy
    strategy, config = EQUIVALENT[name]
    # The options were recorded when a row whose entities may serve two tasks went to one HiGHS solve; the task-by-task
    # search finds covers of the same profit, which may break ties otherwise.
    by_task = search.task_by_task_cover
    monkeypatch.setattr(search, "task_by_task_cover", lambda *a: by_task(*a) if a[4].sum(1).max() <= 1 else None)
    action, _ = model.predict(_obs(saved), deterministic=True, decoder=get_decoding_strategy(strategy, **config))
    np.testing.assert_array_equal(action, saved[f"action_{name}"])
    assert model.policy.decoder.name == "preassign_search"  # a per-call decoder leaves the model's own in place


def test_sampled_equals_the_stochastic_policy(legacy):
    """The ``sampled`` strategy's deterministic decision is the stochastic policy's, on the same seed."""
    model, saved = legacy
    th.manual_seed(7)
    with model.decoding("sampled"):
        action, _ = model.predict(_obs(saved), deterministic=True)
    th.manual_seed(7)
    np.testing.assert_array_equal(action, model.predict(_obs(saved), deterministic=False)[0])
    assert (action != model.predict(_obs(saved), deterministic=False)[0]).any()  # another draw decides otherwise


def test_decoder_is_set_per_model_and_never_saved(tmp_path, legacy):
    model, saved = legacy
    strategy = get_decoding_strategy("team_search", samples=32, temperature=3.0)
    per_call = model.predict(_obs(saved), deterministic=True, decoder=strategy)[0]
    model.set_decoder("team_search", samples=32, temperature=3.0)
    try:
        assert np.array_equal(model.predict(_obs(saved), deterministic=True)[0], per_call)
        model.save(tmp_path / "m.zip")
    finally:
        model.set_decoder("preassign_search", samples=4)
    loaded = TwoStageSAC.load(tmp_path / "m.zip", device="cpu")
    assert loaded.policy.decoder.name == "argmax"
    assert np.array_equal(loaded.predict(_obs(saved), deterministic=True)[0], saved["action_argmax"])


def test_strategies_by_name_and_clear_errors():
    assert {"argmax", "sampled", "preassign_search", "team_search", "exact_covers", "exact_top", "pooled"} <= set(DECODERS)
    with pytest.raises(ValueError, match="unknown decoding strategy 'beam'"):
        get_decoding_strategy("beam")
    with pytest.raises(ValueError, match=r"decoding strategy 'argmax'.*samples"):
        get_decoding_strategy("argmax", samples=3)
    with pytest.raises(ValueError, match="seed"):
        get_decoding_strategy("team_search", seed=-1)
    strategy = get_decoding_strategy("exact_top", top=3)
    assert get_decoding_strategy(strategy) is strategy
    assert get_decoding_strategy(type(strategy).name, **strategy.config).config == strategy.config


def test_each_env_with_a_measured_decoder_gets_it_by_id(legacy):
    """The recommended decoders are settings a model takes (the names and values of docs/options.md), and an env
    without one is named in the error rather than given a guess."""
    for env_id, (name, config) in RECOMMENDED_DECODERS.items():
        gym.spec(env_id)  # a registered id
        decoder = recommended_decoder(env_id)
        assert type(decoder).name == name and {k: decoder.config[k] for k in config} == config
    slots = gym.make("TaskAlloc/MT-v0").observation_space["task_mask"].shape[0]
    assert recommended_decoder("TaskAlloc/MT-v0").config["top"] == slots  # every pair, as the per-step MILP
    model, _ = legacy
    model.set_decoder(recommended_decoder("TaskAlloc/MT-v0"))
    assert model.policy.decoder.config["surcharge"] == 0.64
    with pytest.raises(ValueError, match="no decoder was measured on 'TaskAlloc/EPT-v0'"):
        recommended_decoder("TaskAlloc/EPT-v0")


def test_a_new_strategy_is_one_registered_class(legacy):
    """A strategy registered by name is usable at once: here one that keeps every entity free."""
    model, saved = legacy

    @register_decoder
    class Idle(Decoder):
        name = "idle_for_test"

        def preassign(self, policy, view, dist, first_round):
            return th.full_like(view.entity_mask, -1, dtype=th.long), None

    try:
        action, _ = model.predict(_obs(saved), deterministic=True, decoder="idle_for_test")
        M = saved["task_mask"].shape[1]
        assert (action == M).all()
    finally:
        del DECODERS["idle_for_test"]


def _best_assignment(view, b: int, entities: np.ndarray, cost: np.ndarray) -> float:
    """The most profitable assignment of ``entities`` to the open tasks of state ``b`` (or to none), a task counting only
    where its team covers its demand: Σ_j (r_j − Σ_{i ∈ team j} cost_ij), by enumerating every assignment."""
    tasks = np.flatnonzero(view.task_mask[b].numpy())
    supply, demand, reward = view.supply[b].numpy(), view.demand[b].numpy(), view.reward[b].numpy()
    best = 0.0
    for choice in itertools.product(range(len(tasks) + 1), repeat=len(entities)):
        teams = [entities[np.asarray(choice) == k] for k in range(len(tasks))]
        if any(len(t) and (supply[t].sum(0) < demand[j] - 1e-6).any() for t, j in zip(teams, tasks, strict=True)):
            continue
        best = max(best, sum(float(reward[j]) - float(cost[t, j].sum()) for t, j in zip(teams, tasks, strict=True) if len(t)))
    return best


def _check_best_assignments(view, decision, cost: th.Tensor) -> int:
    """Assert that each state's ``decision`` is worth, at the pair costs ``cost`` (B, N, M), the best of all
    assignments of its free entities enumerated; return how many states had something to decide."""
    team = (decision.pick_rank >= 0) & decision.kept.unsqueeze(-1)  # (B, M, N)
    found = (decision.kept * (view.reward - (team.float() * cost.transpose(1, 2)).sum(-1))).sum(-1)
    checked = 0
    for b in range(view.reward.shape[0]):
        entities = np.flatnonzero(view.entity_mask[b].numpy())
        if len(entities) and bool(view.task_mask[b].any()):
            assert float(found[b]) == pytest.approx(_best_assignment(view, b, entities, cost[b].numpy()), abs=1e-3)
            checked += 1
    return checked


def _visited(model: TwoStageSAC, steps: int = 12):
    """The states of ``steps`` deterministic MT steps from reset seed 5, as one batch's view."""
    env = gym.make("TaskAlloc/MT-v0")
    obs, _ = env.reset(seed=5)
    states = []
    for _ in range(steps):
        states.append(obs)
        obs = env.step(model.predict(obs, deterministic=True)[0])[0]
    policy = model.policy
    return policy.parse(policy.obs_to_tensor({k: np.stack([o[k] for o in states]) for k in states[0]})[0])


@pytest.fixture(scope="module")
def mt_model() -> TwoStageSAC:
    """A small MT model whose pointer has trained a few steps (its decisions are not the rule's alone)."""
    model = TwoStageSAC(
        "TAMPolicy",
        "TaskAlloc/MT-v0",
        policy_kwargs={"hidden_dim": 16},
        train_preassign_actor=False,
        learning_starts=40,
        batch_size=16,
        buffer_size=1000,
        seed=0,
        device="cpu",
    )
    return model.learn(60)


@pytest.mark.parametrize("surcharge", [0.0, 0.08])
def test_an_exact_top_round_keeps_its_covers_teams(mt_model: TwoStageSAC, surcharge: float) -> None:
    """The exact cover of a round's candidate pairs is the candidates themselves (each team of the round's cover is the
    most profitable of its own members), which is why its teams do not solve it again; and without a surcharge the
    teams equal those of the search that does."""
    from sb3_taskalloc.two_stage_sac.decoding import decide_preassigned
    from sb3_taskalloc.two_stage_sac.search import cover_search, exact_covers

    policy = mt_model.policy
    view = _visited(mt_model)
    decoder = get_decoding_strategy("exact_top", top=2, surcharge=surcharge)
    visited: list = []
    with th.no_grad():
        decide_preassigned(policy, view, decoder, visited)
        for round_view, task_of in visited:
            M = round_view.task_mask.shape[1]
            allowed = task_of.unsqueeze(-1) == th.arange(M)
            assert th.equal(exact_covers(decoder.costed(round_view), allowed), task_of)
            rank, kept = decoder.teams(policy, round_view, task_of)
            if surcharge == 0.0:
                solved = cover_search(policy.selector.head, round_view, task_of)
                assert th.equal(rank, solved.rank) and th.equal(kept, solved.profit > 0)
    assert sum(int((c >= 0).sum()) for _, c in visited) >= 10


def test_the_surcharge_raises_every_pair_cost_in_exact_tops_objective(mt_model: TwoStageSAC) -> None:
    """``exact_top(surcharge=σ)`` with every pair allowed (``top`` = M) is worth, at the costs (1 + σ)·c, the best of
    all assignments enumerated, and σ = 0 is ``exact_top`` itself; a negative surcharge is refused by name."""
    from sb3_taskalloc.two_stage_sac.decoding import decide_preassigned

    policy = mt_model.policy
    view = _visited(mt_model, steps=8)
    # Five free trucks per state keep the enumeration small: (M + 1)^5 assignments.
    view = view._replace(entity_mask=view.entity_mask & (view.entity_mask.cumsum(-1) <= 5))
    M, sigma = view.reward.shape[1], 0.5
    cost = view.pair_cost * (1 + sigma)
    with th.no_grad():
        first = decide_preassigned(policy, view, get_decoding_strategy("exact_top", top=M, surcharge=sigma))
        unsurcharged = decide_preassigned(policy, view, get_decoding_strategy("exact_top", top=M))
        plain = decide_preassigned(policy, view, get_decoding_strategy("exact_top", top=2, surcharge=0.0))
        exact = decide_preassigned(policy, view, get_decoding_strategy("exact_top", top=2))
    assert _check_best_assignments(view, first, cost) >= 3
    assert th.equal(plain.env_action, exact.env_action)
    # a surcharge this large leaves some truck home that the plain objective sends
    assert int((first.env_action < M).sum()) < int((unsurcharged.env_action < M).sum())
    with pytest.raises(ValueError, match="surcharge must be a finite number >= 0"):
        get_decoding_strategy("exact_top", surcharge=-0.1)
    assert get_decoding_strategy("exact_top", top=2, surcharge=0.08).config == {"top": 2, "surcharge": 0.08, "seed": 0}


def test_the_removed_future_critic_is_named_with_its_replacement():
    """``mixer="future"`` and its ``value_top`` decoder left the library: the error says what decides as well and
    which commit still loads such a model."""
    with pytest.raises(
        ValueError,
        match=r"mixer='future'.*surcharge=0\.08.*last commit with it is [0-9a-f]{7}\. A model saved with it still loads",
    ):
        TwoStageSAC("TAMPolicy", "TaskAlloc/MT-v0", policy_kwargs={"mixer": "future"}, device="cpu")
    with pytest.raises(ValueError, match="unknown decoding strategy 'value_top'"):
        get_decoding_strategy("value_top")


def test_a_model_saved_with_the_removed_future_critic_loads_and_decides_as_before():
    """A model trained with ``mixer="future"`` (``tests/data/make_future_critic_fixture.py``, commit 986c6cf) loads with
    a warning, its critic as the monotonic AMIX critic whose parameters it has, and decides as it did: by the argmax and
    by the surcharge its user is told to decode with. It trains on."""
    with pytest.warns(UserWarning, match=r"future critic \(mixer='future'\).*surcharge=0\.08"):
        model = TwoStageSAC.load(DATA / "future_critic_mt.zip", env=gym.make("TaskAlloc/MT-v0"), device="cpu")
    assert model.policy.mixer == "amix" and model.policy.mixer_kwargs["monotonic"] is True
    saved = dict(np.load(DATA / "future_critic_decisions.npz"))
    assert np.array_equal(model.predict(_obs(saved), deterministic=True)[0], saved["action_argmax"])
    with model.decoding("exact_top", top=2, surcharge=0.08):
        assert np.array_equal(model.predict(_obs(saved), deterministic=True)[0], saved["action_exact_top_surcharge"])
    model.learn(20)
    assert model._n_updates == 20
