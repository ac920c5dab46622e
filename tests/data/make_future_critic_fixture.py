"""A model saved with the future critic (``mixer="future"``, commit 986c6cf, the last that held it), for the test that
such a model still loads and decides as it did. Run from a checkout of that commit: ``python
tests/data/make_future_critic_fixture.py`` (written to the working directory's tests/data)."""

import gymnasium as gym
import numpy as np

import envs  # noqa
from sb3_taskalloc import TwoStageSAC

env = gym.make("TaskAlloc/MT-v0")
model = TwoStageSAC(
    "TAMPolicy",
    env,
    seed=0,
    buffer_size=200,
    learning_starts=40,
    batch_size=16,
    train_preassign_actor=False,
    policy_kwargs={"mixer": "future", "hidden_dim": 16},
    device="cpu",
)
model.learn(60)
model.save("tests/data/future_critic_mt.zip")
obs_list = []
o, _ = env.reset(seed=5)
for _ in range(4):
    obs_list.append(o)
    o, *_ = env.step(model.predict(o, deterministic=True)[0])
obs = {k: np.stack([x[k] for x in obs_list]) for k in obs_list[0]}
actions = {"action_argmax": model.predict(obs, deterministic=True)[0]}
with model.decoding("exact_top", top=2, surcharge=0.08):
    actions["action_exact_top_surcharge"] = model.predict(obs, deterministic=True)[0]
np.savez_compressed("tests/data/future_critic_decisions.npz", **obs, **actions)
