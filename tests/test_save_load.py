"""Save/load, replay buffer persistence, seeding and size transfer."""

from __future__ import annotations

import pickle

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_taskalloc import TwoStageSAC
from sb3_taskalloc.common.buffers import TwoStageReplayBuffer

SMALL = {"hidden_dim": 16}


def observations(env_id: str, n: int = 5, **kwargs) -> list[dict[str, np.ndarray]]:
    env = gym.make(env_id, **kwargs)
    return [env.reset(seed=s)[0] for s in range(n)]


@pytest.mark.parametrize(
    "kwargs",
    [
        {},
        {"preassign": False},
        {"encoder": "mlp"},
        {"mixer": "global"},
        {"rounds": 2, "mixer_kwargs": {"monotonic": True, "hyper_bias": True, "team_value": False}},
    ],
)
def test_save_load_identical_predict(tmp_path, kwargs):
    model = TwoStageSAC(
        "TAMPolicy", "TaskAlloc/RBF-v0", learning_starts=10, batch_size=8, seed=0, policy_kwargs={**SMALL, **kwargs}
    )
    model.learn(16)
    model.save(tmp_path / "model")
    loaded = TwoStageSAC.load(tmp_path / "model", env=gym.make("TaskAlloc/RBF-v0"))
    assert all(getattr(loaded.policy, k) == v for k, v in kwargs.items())
    for obs in observations("TaskAlloc/RBF-v0"):  # with the searches both draw from their own stream, seeded at 0
        np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    for key, value in model.policy.state_dict().items():
        assert np.array_equal(value.cpu().numpy(), loaded.policy.state_dict()[key].cpu().numpy()), key
    # Entropy coefficients and optimizers come back too; training resumes.
    assert (
        float(loaded.log_ent_coef.detach()) == pytest.approx(float(model.log_ent_coef.detach()))
        if model.log_ent_coef is not None
        else True
    )
    steps = loaded.num_timesteps
    loaded.learn(6, reset_num_timesteps=False)
    assert loaded.num_timesteps == steps + 6


@pytest.mark.parametrize(
    ("decoder", "config"),
    [
        ("preassign_search", {"samples": 8}),
        ("team_search", {"samples": 4}),
        ("exact_covers", {}),
        # top = 1: per-task covers, quick to solve (top = 2 over RBF's 100 robots decides the same after a reload too,
        # as every solve stops at a node limit, but takes about 15 s here)
        ("exact_top", {"top": 1}),
    ],
)
def test_save_load_identical_predict_with_each_decoder(tmp_path, decoder, config):
    """A decoder is no part of the saved model: set on the loaded one, it decides as on the original (the searches draw
    from their own streams, seeded at 0)."""
    model = TwoStageSAC(
        "TAMPolicy", "TaskAlloc/RBF-v0", learning_starts=10, batch_size=8, seed=0, policy_kwargs={**SMALL, "rounds": 2}
    )
    model.learn(16)
    model.save(tmp_path / "model")
    loaded = TwoStageSAC.load(tmp_path / "model")
    for agent in (model, loaded):
        agent.set_decoder(decoder, **config)
    for obs in observations("TaskAlloc/RBF-v0"):
        np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])


def test_replay_buffer_save_load(tmp_path):
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/EPT-v0", learning_starts=20, batch_size=8, seed=0, policy_kwargs=SMALL)
    model.learn(25)
    model.save_replay_buffer(tmp_path / "buffer")
    fresh = TwoStageSAC("TAMPolicy", "TaskAlloc/EPT-v0", seed=1, policy_kwargs=SMALL)
    fresh.load_replay_buffer(tmp_path / "buffer")
    assert fresh.replay_buffer.size() == model.replay_buffer.size() == 25
    np.testing.assert_array_equal(fresh.replay_buffer.pick_steps, model.replay_buffer.pick_steps)
    np.testing.assert_array_equal(fresh.replay_buffer.candidates, model.replay_buffer.candidates)
    assert model.replay_buffer.nbytes_per_transition() > 0
    # A buffer pickled with the pick steps counted from 0 (−1: not picked) loads with the same samples.
    state = dict(vars(model.replay_buffer))
    state["pick_rank"] = state.pop("pick_steps") - 1
    (tmp_path / "old.pkl").write_bytes(pickle.dumps(state))
    old = TwoStageReplayBuffer.__new__(TwoStageReplayBuffer)
    old.__setstate__(pickle.loads((tmp_path / "old.pkl").read_bytes()))
    np.testing.assert_array_equal(old.pick_steps, model.replay_buffer.pick_steps)
    assert (model.replay_buffer.pick_steps[:25] > 0).any() and (model.replay_buffer.pick_steps[:25] == 0).any()


def buffer_arrays(buffer: TwoStageReplayBuffer) -> dict[str, np.ndarray]:
    """Every array of ``buffer``, those of its dict attributes by ``attribute.key``."""
    arrays = {}
    for name, value in vars(buffer).items():
        items = value.items() if isinstance(value, dict) else [(None, value)]
        arrays |= {f"{name}.{k}" if k else name: v for k, v in items if isinstance(v, np.ndarray)}
    return arrays


@pytest.mark.parametrize("steps", [25, 70])
def test_replay_buffer_pickles_only_its_stored_rows(tmp_path, steps):
    """A buffer that is not full is saved with its stored rows only (RBF's 100,000 rows take 2.3 GB whole) and loads
    equal to the saved one, array by array, with room for ``buffer_size`` transitions; a full one is saved whole."""
    model = TwoStageSAC(
        "TAMPolicy", "TaskAlloc/EPT-v0", buffer_size=60, learning_starts=20, batch_size=8, seed=0, policy_kwargs=SMALL
    )
    model.learn(steps)
    model.save_replay_buffer(tmp_path / "buffer")
    loaded = TwoStageSAC("TAMPolicy", "TaskAlloc/EPT-v0", buffer_size=60, seed=1, policy_kwargs=SMALL)
    loaded.load_replay_buffer(tmp_path / "buffer")
    saved, back = buffer_arrays(model.replay_buffer), buffer_arrays(loaded.replay_buffer)
    assert saved.keys() == back.keys() and {"actions", "candidates", "observations.entity_mask"} <= saved.keys()
    for name, array in saved.items():
        assert back[name].dtype == array.dtype, name
        np.testing.assert_array_equal(back[name], array, err_msg=name)
    assert (loaded.replay_buffer.pos, loaded.replay_buffer.full) == (model.replay_buffer.pos, model.replay_buffer.full)
    whole = model.replay_buffer.nbytes_per_transition() * 60
    size = (tmp_path / "buffer.pkl").stat().st_size
    assert size < 0.6 * whole if steps < 60 else size > whole
    loaded.learn(5, reset_num_timesteps=False)  # it samples and stores on from there
    assert loaded.replay_buffer.size() == min(steps + 5, 60)


def test_same_seed_same_run():
    runs = []
    for _ in range(2):
        model = TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", learning_starts=10, batch_size=8, seed=7, policy_kwargs=SMALL)
        model.learn(20)
        runs.append(model)
    a, b = runs
    np.testing.assert_array_equal(a.replay_buffer.actions[:20], b.replay_buffer.actions[:20])
    np.testing.assert_array_equal(a.replay_buffer.rewards[:20], b.replay_buffer.rewards[:20])
    for obs in observations("TaskAlloc/RBF-v0", 3):
        np.testing.assert_array_equal(a.predict(obs, deterministic=True)[0], b.predict(obs, deterministic=True)[0])
    c = TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", learning_starts=10, batch_size=8, seed=8, policy_kwargs=SMALL)
    c.learn(20)
    assert not np.array_equal(a.replay_buffer.actions[:20], c.replay_buffer.actions[:20])


@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_same_seed_same_weights_with_deterministic_algorithms():
    """On CUDA, atomic adds sum in any order, so reruns differ slightly unless PyTorch's deterministic algorithms are
    on (with ``CUBLAS_WORKSPACE_CONFIG`` set, see conftest); then two runs give bit-identical weights."""

    def run() -> th.Tensor:
        model = TwoStageSAC(
            "TAMPolicy", "TaskAlloc/RBF-v0", learning_starts=32, batch_size=32, seed=3, device="cuda", policy_kwargs=SMALL
        )
        model.learn(100)
        return th.cat([p.detach().flatten().cpu() for p in model.policy.parameters()])

    th.use_deterministic_algorithms(True)
    try:
        assert th.equal(run(), run())
    finally:
        th.use_deterministic_algorithms(False)


def test_size_transfer(tmp_path):
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", learning_starts=10, batch_size=8, seed=0, policy_kwargs=SMALL)
    model.learn(12)
    model.save(tmp_path / "tam")
    for env in (gym.make("TaskAlloc/RBF-EntityShift-v0"), gym.make("TaskAlloc/RBF-v0", max_entities=200, max_tasks=12)):
        loaded = TwoStageSAC.load(tmp_path / "tam", env=env)
        obs, _ = env.reset(seed=0)
        action, _ = loaded.predict(obs, deterministic=True)
        assert action.shape == env.action_space.shape
        _, _, _, _, info = env.step(action)
        assert info["invalid_assignments"] == 0
        loaded.learn(4, reset_num_timesteps=False)  # fine-tuning works in the new size


def test_size_specific_policy_refuses(tmp_path):
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", seed=0, policy_kwargs={**SMALL, "encoder": "mlp"})
    model.save(tmp_path / "mlp")
    with pytest.raises(ValueError, match="size-specific"):
        TwoStageSAC.load(tmp_path / "mlp", env=gym.make("TaskAlloc/RBF-EntityShift-v0"))


def test_wrong_env_family_refused(tmp_path):
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", seed=0, policy_kwargs=SMALL)
    model.save(tmp_path / "rbf")
    with pytest.raises(ValueError, match="features per row"):
        TwoStageSAC.load(tmp_path / "rbf", env=gym.make("TaskAlloc/Almighty-v0"))
    with pytest.raises(ValueError, match="TaskAlloc Dict observation space"):
        TwoStageSAC("TAMPolicy", "CartPole-v1")
    almighty = gym.make("TaskAlloc/Almighty-v0")
    almighty.action_space = gym.spaces.MultiDiscrete([3] * 25)  # the observation's layout with the wrong choices
    with pytest.raises(ValueError, match=r"MultiDiscrete\(\[10\] \* 25\)"):
        TwoStageSAC("TAMPolicy", almighty)


def test_vec_normalize_refused():
    from stable_baselines3.common.vec_env import VecNormalize

    venv = VecNormalize(make_vec_env("TaskAlloc/Almighty-v0", n_envs=1), norm_obs=False)
    with pytest.raises(ValueError, match="VecNormalize"):
        TwoStageSAC("TAMPolicy", venv)


def test_state_without_the_priors_is_refused():
    """A policy state without the frozen initial actors is not this policy's: loading it names the missing keys."""
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", seed=0, policy_kwargs={"hidden_dim": 16})
    state = {k: v for k, v in model.policy.state_dict().items() if "_prior." not in k}
    with pytest.raises(RuntimeError, match=r"Missing key.*actor_prior"):
        model.policy.load_state_dict(state)


def test_failed_save_keeps_the_previous_model(tmp_path, monkeypatch):
    """A save that fails midway (here: the disk fills while the zip is written) leaves the previous model whole."""
    import zipfile

    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", seed=0, policy_kwargs={"hidden_dim": 16})
    model.save(tmp_path / "model")
    before = (tmp_path / "model.zip").read_bytes()

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(zipfile.ZipFile, "writestr", disk_full)
    with pytest.raises(OSError, match="No space left"):
        model.save(tmp_path / "model")
    monkeypatch.undo()
    assert (tmp_path / "model.zip").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.zip"]  # no temporary file left behind
    TwoStageSAC.load(tmp_path / "model")


def test_failed_replay_buffer_save_keeps_the_previous_buffer(tmp_path, monkeypatch):
    import pickle

    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", buffer_size=16, learning_starts=5, seed=0, policy_kwargs=SMALL)
    model.learn(5)
    model.save_replay_buffer(tmp_path / "buffer")
    before = (tmp_path / "buffer.pkl").read_bytes()
    monkeypatch.setattr(pickle, "dump", lambda *a, **k: (_ for _ in ()).throw(OSError(27, "File too large")))
    with pytest.raises(OSError, match="File too large"):
        model.save_replay_buffer(tmp_path / "buffer")
    monkeypatch.undo()
    assert (tmp_path / "buffer.pkl").read_bytes() == before


@pytest.mark.parametrize("content", ["truncated", "no_policy", "no_optimizer", "damaged_data"])
def test_broken_save_is_named(tmp_path, content):
    """A truncated zip, one without ``policy.pth`` or an optimizer's state, or with its ``data`` cut, gets an error naming
    the file and what is wrong (SB3 raised a bare ``KeyError`` or ``JSONDecodeError``); the weights of a save without
    its optimizer state still load by the route the message names."""
    import zipfile

    model = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", seed=0, policy_kwargs={"hidden_dim": 16})
    model.save(tmp_path / "model")
    path = tmp_path / "model.zip"
    if content == "truncated":
        path.write_bytes(path.read_bytes()[:200])
    else:
        with zipfile.ZipFile(path) as z:
            members = {n: z.read(n) for n in z.namelist()}
        dropped = {"no_policy": "policy.pth", "no_optimizer": "selector.optimizer.pth"}.get(content)
        members.pop(dropped, None)
        if content == "damaged_data":
            members["data"] = members["data"][: len(members["data"]) // 2]
        with zipfile.ZipFile(path, "w") as z:
            for name, data in members.items():
                z.writestr(name, data)
    match = {
        "truncated": "not a zip file",
        "no_policy": "no policy.pth",
        "no_optimizer": r"lacks saved state .*selector\.optimizer.*set_parameters\(path, exact_match=False\)",
        "damaged_data": "damaged 'data' member",
    }[content]
    with pytest.raises(ValueError, match=match):
        TwoStageSAC.load(path)
    if content == "no_optimizer":
        fresh = TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", seed=1, policy_kwargs={"hidden_dim": 16})
        fresh.set_parameters(str(path), exact_match=False)
        for name, tensor in model.policy.state_dict().items():
            assert th.equal(tensor, fresh.policy.state_dict()[name]), name


def test_replay_buffer_of_another_size_is_refused(tmp_path):
    """A buffer filled on a 100-entity env cannot be trained on by a 50-entity model: refused when loaded."""
    # A buffer of 16 rows: saving the default 100,000 rows of 100-robot observations took 8 of the test's 10 s.
    big = TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", buffer_size=16, learning_starts=3, seed=0, policy_kwargs=SMALL)
    big.learn(3)
    big.save_replay_buffer(tmp_path / "buffer")
    small = TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-EntityShift-v0", seed=0, policy_kwargs=SMALL)
    buffer = small.replay_buffer
    with pytest.raises(ValueError, match="filled on another env"):
        small.load_replay_buffer(tmp_path / "buffer")
    assert small.replay_buffer is buffer


def test_bad_observations_to_predict_are_named():
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/EPT-v0", seed=0, policy_kwargs=SMALL)
    obs = observations("TaskAlloc/EPT-v0", 1)[0]
    nan = {**obs, "entity_features": obs["entity_features"].copy()}
    nan["entity_features"][0, 0] = np.nan
    with pytest.raises(ValueError, match=r"observation\['entity_features'\] contains NaN"):
        model.predict(nan)
    with pytest.raises(ValueError, match=r"unexpected \['foo'\]"):
        model.predict({**obs, "foo": np.zeros(3)})
    with pytest.raises(ValueError, match=r"missing \['pair_cost'\]"):
        model.predict({k: v for k, v in obs.items() if k != "pair_cost"})


def test_an_observation_of_another_size_names_the_sizes_and_the_remedy():
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", seed=0, policy_kwargs=SMALL)
    shifted = gym.make("TaskAlloc/RBF-EntityShift-v0")
    obs, _ = shifted.reset(seed=0)
    n, m = len(obs["entity_mask"]), len(obs["task_mask"])
    N, M = (model.observation_space[key].shape[0] for key in ("entity_mask", "task_mask"))
    assert n != N
    with pytest.raises(ValueError, match=rf"has {n} entities and {m} tasks, the model's space {N} and {M}.*set_env"):
        model.predict(obs)
    with pytest.raises(ValueError, match=rf"has {n} entities"):  # a batch of them is named alike
        model.predict({k: np.stack([v, v]) for k, v in obs.items()})
    with pytest.raises(ValueError, match=r"disagree on its size: 10 entities in entity_mask"):  # malformed, not resized
        model.predict({**obs, "entity_mask": obs["entity_mask"][:10]})
    model.set_env(shifted)  # the remedy the message names
    assert model.predict(obs, deterministic=True)[0].shape == (n,)


def test_load_and_set_env_take_an_env_id_as_the_constructor_does(tmp_path):
    """``TwoStageSAC.load(path, env="TaskAlloc/RBF-EntityShift-v0")`` and ``set_env(id)``: the id is made as the
    constructor makes it, where SB3 refused a string as "not a Gymnasium environment"."""
    TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0", seed=0, policy_kwargs=SMALL).save(tmp_path / "rbf")
    shifted_id = "TaskAlloc/RBF-EntityShift-v0"
    obs, _ = gym.make(shifted_id).reset(seed=0)
    loaded = TwoStageSAC.load(tmp_path / "rbf", env=shifted_id)
    assert loaded.get_env() is not None and loaded.observation_space == gym.make(shifted_id).observation_space
    assert loaded.predict(obs, deterministic=True)[0].shape == (len(obs["entity_mask"]),)
    loaded.set_env("TaskAlloc/RBF-v0")
    assert loaded.observation_space == gym.make("TaskAlloc/RBF-v0").observation_space
