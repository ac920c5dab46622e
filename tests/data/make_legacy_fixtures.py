"""Fixtures made with the constructor-option decoders (commit 632165d), for the decoding-strategy tests."""

import gymnasium as gym
import numpy as np
import torch as th

import envs  # noqa
from sb3_taskalloc import TwoStageSAC

env = gym.make("TaskAlloc/RBF-v0")
model = TwoStageSAC(
    "TAMPolicy",
    env,
    seed=0,
    buffer_size=64,
    learning_starts=8,
    batch_size=8,
    policy_kwargs={"rounds": 2, "decision_samples": 4, "hidden_dim": 16},
)
model.learn(16)
model.save("tests/data/legacy_rbf_decision_samples4.zip")
obs_list = []
o, _ = env.reset(seed=123)
for _ in range(3):
    obs_list.append(o)
    o, *_ = env.step(model.predict(o, deterministic=True)[0])
obs = {k: np.stack([x[k] for x in obs_list]) for k in obs_list[0]}
options = {
    "argmax": {},
    "preassign_search": {"decision_samples": 8, "decision_temperature": 2.0},
    "team_search": {"select_decision_samples": 32, "select_decision_temperature": 3.0},
    "exact_covers": {"select_decision_exact": True},
    "team_search_exact": {"select_decision_samples": 8, "select_decision_exact": True},
    "exact_top1": {"decision_exact_top": 1},
    "exact_top2": {"decision_exact_top": 2},
}
defaults = dict(
    decision_samples=1,
    decision_temperature=2.0,
    select_decision_samples=1,
    select_decision_temperature=1.0,
    select_decision_exact=False,
    decision_exact_top=0,
)
out = {k: v for k, v in obs.items()}
pol = model.policy
for name, opts in options.items():
    for k, v in {**defaults, **opts}.items():
        setattr(pol, k, v)
    pol._search_stream = None
    out["action_" + name] = pol.predict(obs, deterministic=True)[0]
for k, v in defaults.items():
    setattr(pol, k, v)
th.manual_seed(7)
out["action_sampled"] = pol.predict(obs, deterministic=False)[0]
np.savez_compressed("tests/data/legacy_decisions.npz", **out)
print({k: v.shape for k, v in out.items()})
for n in options:
    print(n, (out["action_" + n] != out["action_argmax"]).sum())
