"""Bidding workers: bids in range, wages paid as charged, determinism, co-training, the market check."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest
import torch as th

from envs.rendering import random_valid_action
from sb3_taskalloc import TwoStageSAC
from sb3_taskalloc.baselines import GreedyAllocator
from sb3_taskalloc.experiments.cotrain import co_train, run_manager
from sb3_taskalloc.market import BiddingWorkers, WorkerMarket, make_market, worker_observations


class RandomManager:
    """Random valid allocations that never pick the second half of the entities."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def predict(self, obs, state=None, episode_start=None, deterministic=True):
        action = random_valid_action(obs, self.rng)
        n = len(action)
        action[n // 2 :] = obs["task_mask"].shape[0]
        return action, None


def test_market_needs_a_bidding_env():
    env = gym.make("TaskAlloc/RBF-v0")
    with pytest.raises(ValueError, match="bidding=True"):
        WorkerMarket(env, BiddingWorkers(3, 3.0))
    with pytest.raises(ValueError, match="bid_max"):
        WorkerMarket(gym.make("TaskAlloc/RBF-v0", bidding=True), BiddingWorkers(3, 5.0))
    with pytest.raises(ValueError, match="init_bid"):
        BiddingWorkers(3, 3.0, init_bid=4.0)


@pytest.mark.parametrize("env_id", ["TaskAlloc/RBF-v0", "TaskAlloc/MT-v0"])
def test_bids_in_range_and_wages_are_the_charged_costs(env_id):
    env = gym.make(env_id, bidding=True, travel_cost=0.0)  # no travel: the env charges exactly the accepted bids
    workers = BiddingWorkers(env.unwrapped.K, env.unwrapped.bid_max, seed=0, learning_starts=10**9)
    workers.sigma = env.unwrapped.bid_max  # wide noise: bids hit both bounds
    market = WorkerMarket(env, workers)
    manager = RandomManager(0)
    obs, _ = market.reset(seed=0)
    earned = np.zeros(env.unwrapped.max_entities)
    wage_at_commit: dict[int, float] = {}
    seen_zero = seen_max = False
    for _ in range(150):
        bids = market.last_bids
        assert np.all(bids >= 0) and np.all(bids <= env.unwrapped.bid_max)
        seen_zero |= float(bids.min()) == 0.0
        seen_max |= float(bids.max()) == env.unwrapped.bid_max
        np.testing.assert_allclose(obs["entity_features"][:, -1], bids, rtol=1e-6)  # the manager sees the bids
        action, _ = manager.predict(obs)
        obs, _, term, trunc, info = market.step(action)
        applied = env.unwrapped.applied_action()
        for i in np.flatnonzero(applied < env.unwrapped.max_tasks):
            wage_at_commit[int(i)] = float(bids[i])
        # Independent sum: the wages paid this step equal the costs the env charged, entity by entity.
        np.testing.assert_allclose(info["worker_wages"], info["entity_income"], rtol=1e-9, atol=1e-12)
        assert info["worker_wages"].sum() == pytest.approx(info["cost_total"])
        for i in np.flatnonzero(info["worker_wages"]):
            assert info["worker_wages"][i] == pytest.approx(wage_at_commit[int(i)])
        earned += info["worker_wages"]
        if term or trunc:
            break
    assert seen_zero and seen_max
    never_picked = np.setdiff1d(np.arange(env.unwrapped.n_entities), list(wage_at_commit))
    assert never_picked.size >= env.unwrapped.n_entities // 2 and np.all(
        earned[never_picked] == 0
    )  # a worker never selected earns 0
    assert earned.sum() > 0


def test_worker_observations_offer_the_nearest_open_task():
    env = gym.make("TaskAlloc/RBF-v0", bidding=True)
    obs, _ = env.reset(seed=3)
    idx, task, x = worker_observations(obs, env.unwrapped.base_costs, env.unwrapped.layout)
    K = 3
    assert np.array_equal(idx, np.flatnonzero(obs["entity_mask"])) and x.shape == (len(idx), 2 * K + 8)
    pe = obs["entity_features"][idx, 1 + K : 3 + K]
    pt = obs["task_features"][:, 1 + K : 3 + K]
    d = np.abs(pe[:, None] - pt[None]).sum(-1) + np.where(obs["task_mask"], 0, np.inf)
    np.testing.assert_array_equal(d[np.arange(len(idx)), task], d.min(1))


def run_co_training(seed: int) -> tuple[TwoStageSAC, WorkerMarket]:
    # On the CPU: bit-identical reruns are a CPU property (CUDA's atomic adds sum in any order).
    bid_max = gym.make("TaskAlloc/RBF-v0", bidding=True).unwrapped.bid_max
    workers = BiddingWorkers(3, bid_max, seed=seed, learning_starts=200, batch_size=32, device="cpu")
    kwargs = {
        "learning_starts": 30,
        "batch_size": 16,
        "select_kwargs": {"batch_size": 4},
        "policy_kwargs": {"hidden_dim": 16},
        "device": "cpu",
    }
    return co_train("TaskAlloc/RBF-v0", 60, workers=workers, seed=seed, manager_kwargs=kwargs)


def params(module: th.nn.Module) -> th.Tensor:
    return th.cat([p.detach().flatten().clone() for p in module.parameters()])


def test_co_training_is_deterministic_and_trains_both():
    th.manual_seed(123)
    workers_before = BiddingWorkers(3, 3.0, seed=0, learning_starts=200, batch_size=32, device="cpu")
    manager, market = run_co_training(0)
    manager2, market2 = run_co_training(0)
    assert th.equal(params(manager.policy), params(manager2.policy))
    assert th.equal(params(market.workers.ddpg.actor), params(market2.workers.ddpg.actor))
    assert market.workers.ddpg._n_updates > 0 and manager._n_updates > 0
    assert not th.equal(params(market.workers.ddpg.actor), params(workers_before.ddpg.actor))
    fresh = TwoStageSAC(
        "TAMPolicy", make_market("TaskAlloc/RBF-v0", seed=0), seed=0, policy_kwargs={"hidden_dim": 16}, device="cpu"
    )
    assert not th.equal(params(manager.policy), params(fresh.policy))


@pytest.mark.parametrize("kwargs", [{}, {"policy_kwargs": {"net_arch": [32]}, "learning_rate": 1e-3, "buffer_size": 500}])
def test_save_and_load_workers(tmp_path, kwargs):
    """Workers load as they were saved, their DDPG settings included (a network of another shape than the default
    failed to load when only the market's settings were saved)."""
    workers = BiddingWorkers(3, 3.0, seed=0, **kwargs)
    workers.sigma = 0.2
    workers.save(tmp_path / "workers")
    loaded = BiddingWorkers.load(tmp_path / "workers")
    x = np.random.default_rng(0).standard_normal((7, 14)).astype(np.float32)
    np.testing.assert_allclose(loaded.bid(x, explore=False), workers.bid(x, explore=False))
    assert loaded.sigma == pytest.approx(0.2)
    assert loaded.ddpg.learning_rate == workers.ddpg.learning_rate and loaded.ddpg.buffer_size == workers.ddpg.buffer_size


def frozen_market_stats(workers: BiddingWorkers, seed: int) -> tuple[float, float]:
    """Mean deterministic bid and number of picked bids over one episode with a frozen greedy manager."""
    market = make_market("TaskAlloc/RBF-v0", workers, train=False, explore=False)
    run_manager(market, GreedyAllocator(), 100, seed=seed)
    return market.history[0]["mean_bid"], market.history[0]["picked"]


@pytest.mark.slow
def test_workers_raise_bids_but_stay_picked():
    """Market equilibrium with a frozen greedy manager that prefers cheaper entities: the workers' bids rise from
    their start, but stay low enough that they keep being picked (figures in the README)."""
    workers = BiddingWorkers(3, 3.0, seed=0)
    bid0, picked0 = frozen_market_stats(workers, seed=100)
    co_train("TaskAlloc/RBF-v0", 3000, GreedyAllocator(), workers, seed=0)
    bid1, picked1 = frozen_market_stats(workers, seed=100)
    print(f"\nmean bid {bid0:.3f} -> {bid1:.3f}; picked bids per episode {picked0:.0f} -> {picked1:.0f}")
    assert bid1 > 1.5 * bid0
    assert picked1 > 0.7 * picked0


def test_ddpg_config_blocks_build_workers(tmp_path):
    from pathlib import Path

    from sb3_taskalloc.market import load_worker_config

    path = Path(__file__).resolve().parents[1] / "zoo_configs/ddpg.yml"
    for env_id in ("TaskAlloc/RBF-v0", "TaskAlloc/MT-v0"):
        base = gym.make(env_id, bidding=True).unwrapped
        workers = BiddingWorkers(base.K, base.bid_max, **load_worker_config(path, env_id))
        assert 0 < workers.init_bid < workers.bid_max and workers.sigma >= workers.sigma_min
    bad = tmp_path / "bad.yml"
    bad.write_text("TaskAlloc/RBF-v0:\n  learning_rat: 0.1\n")
    with pytest.raises(ValueError, match="learning_rat"):
        load_worker_config(bad, "TaskAlloc/RBF-v0")


def test_cli_with_a_frozen_greedy_manager(tmp_path, capsys):
    from sb3_taskalloc.workers import main  # the CLI entry point

    main(["--manager", "greedy", "--timesteps", "120", "--out", str(tmp_path), "--seed", "1"])
    assert "co-training, manager frozen" in capsys.readouterr().err  # a progress bar, as a learning manager has
    rows = (tmp_path / "incomes.csv").read_text().strip().splitlines()
    assert len(rows) == 2 and rows[0].startswith("episode,manager_income,worker_income,total_income")
    assert (tmp_path / "incomes.png").stat().st_size > 0 and (tmp_path / "workers.zip").exists()


def test_workers_make_no_log_folder(tmp_path, monkeypatch):
    """The workers' DDPG logs nothing, and makes no folder for it (SB3's ``configure()`` makes ``SB3-<time>`` in the
    temporary folder at every call)."""
    import tempfile

    monkeypatch.delenv("SB3_LOGDIR", raising=False)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    workers = BiddingWorkers(3, 3.0, seed=0, learning_starts=5, batch_size=4)
    co_train("TaskAlloc/RBF-v0", 20, GreedyAllocator(), workers, seed=0)
    assert workers.ddpg._n_updates > 0 and not list(tmp_path.glob("SB3-*"))


def test_frozen_manager_does_not_learn():
    market = make_market("TaskAlloc/RBF-v0", seed=0)
    manager = TwoStageSAC("TAMPolicy", market, seed=0, learning_starts=5, batch_size=8, policy_kwargs={"hidden_dim": 16})
    before = params(manager.policy)
    workers = BiddingWorkers(3, market.workers.bid_max, seed=0, learning_starts=50, batch_size=16)
    _, market = co_train("TaskAlloc/RBF-v0", 30, manager, workers, train_manager=False, seed=0)
    assert th.equal(params(manager.policy), before) and manager._n_updates == 0
    assert workers.ddpg._n_updates > 0  # the workers learned against it


def test_cli_reports_only_the_files_it_wrote(tmp_path, capsys):
    """Too few steps to end an episode: no incomes file exists, and the CLI says so instead of claiming it."""
    from sb3_taskalloc.workers import main

    main(["--manager", "greedy", "--timesteps", "30", "--out", str(tmp_path / "o9")])
    out = capsys.readouterr().out
    assert sorted(p.name for p in (tmp_path / "o9").iterdir()) == ["workers.json", "workers.zip"]
    assert "incomes.csv" not in out.splitlines()[-1] and "workers.zip" in out.splitlines()[-1]
    assert "no episode ended" in out


def test_cli_checks_its_inputs_before_training(tmp_path, monkeypatch):
    from sb3_taskalloc.experiments import cotrain
    from sb3_taskalloc.workers import main

    monkeypatch.setattr(cotrain, "co_train", lambda *a, **k: pytest.fail("trained before the inputs were checked"))
    with pytest.raises(SystemExit):
        main(["--manager", "greedy", "--conf-file", str(tmp_path / "nosuch.yml"), "--out", str(tmp_path)])
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(SystemExit, match="cannot write to --out"):
        main(["--manager", "greedy", "--out", str(blocker / "sub")])
    bad_conf = tmp_path / "bad.yml"
    bad_conf.write_text("TaskAlloc/RBF-v0:\n  learning_rat: 0.1\n")
    for wrong in (
        ["--manager", str(tmp_path / "nosuch.zip")],
        ["--manager", "greedy", "--workers", str(tmp_path / "nosuch")],
        ["--manager", "greedy", "--conf-file", str(bad_conf)],
        ["--env", "Foo"],
    ):
        with pytest.raises(SystemExit) as refused:
            main([*wrong, "--out", str(tmp_path / "o")])
        assert refused.value.code == 2  # argparse's usage error, named, instead of a traceback from the run
    assert not (tmp_path / "o").exists()


def test_default_worker_config_does_not_depend_on_the_current_folder(tmp_path, monkeypatch):
    """Started outside the repository, the CLI still reads the repository's DDPG settings (MT's σ 5.0, not 0.5)."""
    from sb3_taskalloc.experiments import cotrain
    from sb3_taskalloc.market import load_worker_config

    seen = {}

    def fake(env_id, steps, manager, workers, **kwargs):
        seen.update(kwargs["worker_kwargs"])
        raise SystemExit(0)

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(cotrain, "co_train", fake)
    with pytest.raises(SystemExit):
        cotrain.main(["--env", "TaskAlloc/MT-v0", "--manager", "greedy", "--out", str(tmp_path / "o")])
    assert seen == load_worker_config(cotrain.DEFAULT_CONF, "TaskAlloc/MT-v0") and seen


def test_cli_resumes_after_a_kill_and_after_ctrl_c(tmp_path, monkeypatch, capsys):
    """Co-training saves a checkpoint every ``--checkpoint-every`` steps and at Ctrl-C, and the same command started
    again continues from it: a kill (any error but Ctrl-C) loses the steps since the last checkpoint, Ctrl-C none."""
    from sb3_taskalloc.experiments import cotrain

    argv = ["--env", "TaskAlloc/MT-v0", "--timesteps", "60", "--checkpoint-every", "20", "--out", str(tmp_path)]
    hook = cotrain.Checkpoints.hook

    def stop_at(step: int, error: type[BaseException]) -> None:
        def stopping(self, *args):
            hook(self, *args)
            if self.steps == step:
                raise error

        monkeypatch.setattr(cotrain.Checkpoints, "hook", stopping)

    stop_at(45, RuntimeError)  # as a kill: nothing runs after it
    with pytest.raises(RuntimeError):
        cotrain.main(argv)
    (folder,) = tmp_path.glob("checkpoint_*")
    assert json.loads((folder / "state.json").read_text())["steps"] == 40
    assert sorted(p.name for p in folder.iterdir()) == ["state.json", "step_40"]
    saved = ["manager.zip", "manager_buffer.pkl", "workers.json", "workers.zip", "workers_buffer.pkl"]
    assert sorted(p.name for p in (folder / "step_40").iterdir()) == saved
    stop_at(50, KeyboardInterrupt)
    with pytest.raises(SystemExit) as stopped:
        cotrain.main(argv)
    assert stopped.value.code == 130
    out = capsys.readouterr().out
    assert "resuming from the checkpoint at step 40 of 60" in out and "interrupted at step 50 of 60" in out
    assert TwoStageSAC.load(tmp_path / "manager.zip").num_timesteps == 50  # what Ctrl-C stopped is saved
    assert sorted(p.name for p in folder.iterdir()) == ["state.json", "step_50"]
    seen = []

    def watching(self, *args):
        hook(self, *args)
        seen.append(args[1])

    monkeypatch.setattr(cotrain.Checkpoints, "hook", watching)
    cotrain.main(argv)
    assert "resuming from the checkpoint at step 50 of 60" in capsys.readouterr().out
    assert seen[-1].replay_buffer.size() == 60  # the resumed manager's buffer holds the steps before the checkpoint too
    assert TwoStageSAC.load(tmp_path / "manager.zip").num_timesteps == 60
    assert not folder.exists()  # a finished run leaves no checkpoint
    cotrain.main([*argv[:-2], "--seed", "1", "--out", str(tmp_path)])  # other arguments: a new run
    assert "resuming" not in capsys.readouterr().out


def test_co_training_returns_what_it_made_after_ctrl_c():
    """Ctrl-C during co-training returns the manager it made and the market as they stand, with a warning, where the
    exception would lose them (the caller holds neither)."""

    def ctrl_c_at_7(step, manager, market):
        if step == 7:
            raise KeyboardInterrupt

    kwargs = {"learning_starts": 3, "batch_size": 4, "policy_kwargs": {"hidden_dim": 16}}
    with pytest.warns(UserWarning, match="interrupted"):
        manager, market = co_train("TaskAlloc/RBF-v0", 50, seed=0, manager_kwargs=kwargs, hook=ctrl_c_at_7)
    assert manager.num_timesteps == 7 and manager._n_updates > 0 and market.workers is not None


def test_each_checkpoint_draws_the_incomes_so_far(tmp_path, monkeypatch):
    """A long co-training run can be watched: every checkpoint writes the finished episodes' incomes and their figure,
    and a kill leaves them in place."""
    from sb3_taskalloc.experiments import cotrain

    hook = cotrain.Checkpoints.hook

    def killed_at_120(self, *args):
        hook(self, *args)
        if self.steps == 120:
            raise RuntimeError

    monkeypatch.setattr(cotrain.Checkpoints, "hook", killed_at_120)
    with pytest.raises(RuntimeError):
        cotrain.main(["--manager", "greedy", "--timesteps", "150", "--checkpoint-every", "110", "--out", str(tmp_path)])
    rows = (tmp_path / "incomes.csv").read_text().strip().splitlines()
    assert len(rows) == 2 and (tmp_path / "incomes.png").stat().st_size > 0  # RBF's first episode ended at step 100
