"""The stage-1 critic measured against returns (:func:`.diagnose.diagnose`): calibration of state values against one
rollout's and the expected return, and its preferences between two decisions of a state against their paired branch
returns."""

from __future__ import annotations

import copy
import math
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np
import torch as th

from sb3_taskalloc.common.torch_layers import ObsView
from sb3_taskalloc.two_stage_sac.losses import state_entropy
from sb3_taskalloc.two_stage_sac.select_stage import Decision


def _discounted(values: np.ndarray, gamma: float) -> np.ndarray:
    out = np.zeros_like(values)
    acc = 0.0
    for t in range(len(values) - 1, -1, -1):
        acc = values[t] + gamma * acc
        out[t] = acc
    return out


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    if len(a) < 2 or a.std() == 0 or b.std() == 0:
        return float("nan")
    return float(np.corrcoef(a, b)[0, 1])


def _stack(observations: list[dict[str, np.ndarray]], device: th.device) -> dict[str, th.Tensor]:
    return {k: th.as_tensor(np.stack([o[k] for o in observations]), device=device) for k in observations[0]}


def _horizon(gamma: float) -> int:
    """Steps until the discount γ^k falls below 1 %: how far the critic's returns are summed."""
    return math.ceil(math.log(0.01) / math.log(gamma))


def unlimited_env(env_id: str, gamma: float) -> tuple[gym.Env, int | None]:
    """``env_id`` with its time limit extended by :func:`_horizon` (the critic's returns do not stop at the limit), and
    the limit proper (None without one)."""
    limit = gym.spec(env_id).max_episode_steps
    if limit is None:
        return gym.make(env_id), None
    return gym.make(env_id, max_episode_steps=limit + _horizon(gamma)), limit


def _learned_reward(model: Any, reward: SupportsFloat, info: dict[str, Any]) -> float:
    """The reward the stage-1 critic learns: the env reward, or the commitment reward (see the module docstring)."""
    if getattr(model, "reward_timing", "completion") == "commitment":
        return float(info["commitment_reward"])
    return float(reward)


def _branch_returns(model: Any, snapshot: gym.Env, action: np.ndarray, branches: int, horizon: int, key: int) -> np.ndarray:
    """Discounted returns of ``branches`` copies of ``snapshot`` that take ``action`` and then sample the model's
    decisions for ``horizon`` − 1 more steps (or until they end); copy k draws the env's randomness from seed
    ``[key, k]``. The copies decide in one batched forward pass per step."""
    policy, gamma = model.policy, float(model.gamma)
    copies, obs = [], []
    returns, alive = np.zeros(branches), np.ones(branches, dtype=bool)
    for k in range(branches):
        env = copy.deepcopy(snapshot)
        env.unwrapped.np_random = np.random.default_rng([key, k])
        o, reward, terminated, truncated, info = env.step(action)
        returns[k] = _learned_reward(model, reward, info)
        alive[k] = not (terminated or truncated)
        copies.append(env)
        obs.append(o)
    for step in range(1, horizon):
        live = np.flatnonzero(alive)
        if len(live) == 0:
            break
        batch = {name: np.stack([obs[k][name] for k in live]) for name in obs[0]}
        decision = policy.decide(policy.parse(policy.obs_to_tensor(batch)[0]), deterministic=False)
        for row, k in enumerate(live.tolist()):
            obs[k], reward, terminated, truncated, info = copies[k].step(decision.env_action[row].cpu().numpy())
            returns[k] += gamma**step * _learned_reward(model, reward, info)
            alive[k] = not (terminated or truncated)
    return returns


@th.no_grad()
def branch_calibration(
    model: Any, env_id: str, seeds: list[int], branches: int = 8, stride: int = 10, progress: bool = False
) -> dict[str, Any]:
    """The critic against the expected return (see the module docstring): the figures ``branch_states``,
    ``q_corr_expected``, ``q_scale_expected``, ``return_ceiling``, ``free_corr_q`` and ``free_corr_expected`` of
    :class:`Diagnosis`, and the ``advantage_*`` figures of :func:`advantage_figures`, measured on sampled episodes with
    reset seeds ``seeds`` (NaN without a pre-assign critic).

    :param branches: rollouts per state (≥ 2: the ceiling needs their spread)
    :param stride: every ``stride``-th state of an episode is branched
    :param progress: a progress bar over the episodes (each takes minutes on RBF)
    """
    from tqdm.auto import tqdm

    if branches < 2 or stride < 1:
        raise ValueError(f"branches must be >= 2 and stride >= 1, got {branches} and {stride}")
    policy, gamma = model.policy, float(model.gamma)
    nan = float("nan")
    out: dict[str, Any] = dict(branch_states=0, q_corr_expected=nan, q_scale_expected=nan, return_ceiling=nan)
    out.update(free_corr_q=nan, free_corr_expected=nan, advantage_pairs=0, advantage_corr=nan, advantage_ceiling=nan)
    out.update(advantage_sign=nan, advantage_ties=0)
    if policy.actor is None or policy.critic is None:
        return out
    env, limit = unlimited_env(env_id, gamma)
    cuda = [model.device.index or 0] if model.device.type == "cuda" else []
    q, returns, free, gaps, gap_returns = [], [], [], [], []
    for s in tqdm(seeds, desc="branched episodes", disable=not progress):
        obs, _ = env.reset(seed=s)
        for t in range(limit if limit is not None else 10**9):
            view = policy.parse(policy.obs_to_tensor(obs)[0])
            decision = policy.decide(view, deterministic=False)
            action = decision.env_action[0].cpu().numpy()
            if t % stride == 0 and bool(view.assignable.any()):
                key = 1_000 * s + t
                q_c = _critic_value(policy, view, decision)
                q.append(q_c)
                returns.append(_branch_returns(model, env, action, branches, _horizon(gamma), key=key))
                free.append(float(view.assignable.sum()))
                # The alternative draws from its own seeded stream: the figures above stay those of the stream alone.
                with th.random.fork_rng(devices=cuda):
                    th.manual_seed(key)
                    other = policy.decide(view, deterministic=False)
                    if not th.equal(other.candidates, decision.candidates):
                        alt = _branch_returns(model, env, other.env_action[0].cpu().numpy(), branches, _horizon(gamma), key)
                        gaps.append(q_c - _critic_value(policy, view, other))
                        gap_returns.append(returns[-1] - alt)
            obs, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                break
    if len(q) < 2:
        return {**out, "branch_states": len(q)}
    figures = calibration_figures(np.asarray(q), np.stack(returns), np.asarray(free))
    # The measurements themselves, for the diagnosis's plot: (Q, Ḡ) per state and (ΔQ, ΔḠ) per decision pair.
    figures["state_points"] = [(float(v), float(g.mean())) for v, g in zip(q, returns, strict=True)]
    figures["pair_points"] = [(float(v), float(d.mean())) for v, d in zip(gaps, gap_returns, strict=True)]
    if len(gaps) >= 2:
        figures.update(advantage_figures(np.asarray(gaps), np.stack(gap_returns)))
    else:
        figures.update(advantage_pairs=len(gaps), advantage_corr=nan, advantage_ceiling=nan, advantage_sign=nan)
        figures.update(advantage_ties=0)
    return figures


def _critic_value(policy: Any, view: ObsView, decision: Decision) -> float:
    """Q(s, c) = min_k AMIX^k(c) of one state's decision, by its candidate sets c."""
    values = policy.critic(view, decision.candidates.transpose(1, 2).float())
    return float(th.stack(values, 0).min(0).values.item())


def advantage_figures(gaps: np.ndarray, differences: np.ndarray) -> dict[str, Any]:
    """The critic's preference between two decisions of a state against the returns they lead to.

    With the branches of both decisions paired by their env seeds, d_k = G_k(c) − G_k(c′) = Δμ + ε_k. The paired means
    d̄ estimate Δμ = E[G|s,c] − E[G|s,c′] with noise Var(ε)/K, so a critic whose ΔQ equals Δμ correlates with d̄ by
    sqrt(Var Δμ / Var d̄): the ceiling of corr(ΔQ, ΔḠ). Same sign: the share of pairs whose ΔQ and d̄ agree in sign,
    i.e. where the critic prefers the decision whose branches did better, among the pairs whose branches differ:
    two decisions whose every branch returned the same (the pointer sent the same teams, and nothing after differed)
    have no order to agree with, and are counted as ``advantage_ties`` instead.

    :param gaps: (P,) Q(s, c) − Q(s, c′) of the decision pairs
    :param differences: (P, K) the paired branch returns G_k(c) − G_k(c′)
    """
    if differences.ndim != 2 or differences.shape[1] < 2 or len(gaps) != len(differences):
        raise ValueError(f"need (P,) gaps and (P, K >= 2) paired differences, got {gaps.shape} and {differences.shape}")
    mean = differences.mean(1)
    noise = float(differences.var(1, ddof=1).mean()) / differences.shape[1]  # Var of a pair's mean around Δμ
    total = float(mean.var(ddof=1))
    ordered = np.abs(differences).max(1) > 1e-9  # some branch told the two decisions apart
    return dict(
        advantage_pairs=len(gaps),
        advantage_corr=_corr(gaps, mean),
        advantage_ceiling=math.sqrt(max(total - noise, 0.0) / total) if total > 0 else float("nan"),
        advantage_sign=float(np.mean(np.sign(gaps[ordered]) == np.sign(mean[ordered]))) if ordered.any() else math.nan,
        advantage_ties=int((~ordered).sum()),
    )


def calibration_figures(q: np.ndarray, returns: np.ndarray, free: np.ndarray) -> dict[str, Any]:
    """The figures of :func:`branch_calibration` from its measurements.

    With G = μ(s, c) + ε, the branch means Ḡ estimate μ; E Var(ε) is the mean within-state variance s² of the branches,
    and Var μ = Var Ḡ − s²/K (the means keep 1/K of the noise). A critic equal to μ correlates with one rollout's G by
    sqrt(Var μ / (Var μ + E Var ε)): the ceiling.

    :param q: (S,) Q(s, c) of the branched states
    :param returns: (S, K) the branches' discounted returns
    :param free: (S,) the number of free entities of each state
    """
    if returns.ndim != 2 or returns.shape[1] < 2 or len(q) != len(returns) or len(free) != len(returns):
        raise ValueError(f"need (S,) values and (S, K >= 2) returns, got {q.shape}, {returns.shape}, {free.shape}")
    mean = returns.mean(1)
    noise = float(returns.var(1, ddof=1).mean())  # E Var(G | s, c)
    signal = max(float(mean.var(ddof=1)) - noise / returns.shape[1], 0.0)  # Var E[G | s, c]
    return dict(
        branch_states=len(q),
        q_corr_expected=_corr(q, mean),
        q_scale_expected=float(q @ mean / max(mean @ mean, 1e-12)),
        return_ceiling=math.sqrt(signal / (signal + noise)) if signal + noise > 0 else float("nan"),
        free_corr_q=_corr(q, free),
        free_corr_expected=_corr(mean, free),
    )


@th.no_grad()
def critic_figures(model: Any, sampled: list[dict[str, Any]], within: slice, learned: str, alpha: float) -> dict[str, Any]:
    """The stage-1 critic on the states of ``sampled`` episodes (within the time limit): Q against the discounted
    return of the reward it learns (``learned``) and against the entropy-inclusive return, the target's entropy bonus,
    and the actor against its initial rule (KL per free entity, the share whose argmax changed)."""
    policy, gamma = model.policy, float(model.gamma)
    figures: dict[str, Any] = {}
    q, g, g_soft, bonus, kl, changed = [], [], [], [], [], []
    for e in sampled:
        view = policy.parse(_stack(e["obs"], model.device))
        dist = policy.actor(view)
        per_entity = getattr(model, "entropy_bonus", "sum") == "mean"
        entropy = state_entropy(dist, view, per_entity).cpu().numpy()  # the bonus's H(s_t) for t = 0..T
        bonus_t = gamma * alpha * entropy[1:] * (1 - np.r_[np.zeros(len(e["rewards"]) - 1), float(e["terminated"])])
        bonus.append(bonus_t[within])
        g.append(_discounted(e[learned], gamma)[within])
        g_soft.append(_discounted(e[learned] + bonus_t, gamma)[within])
        n = len(g[-1])
        states = ObsView(*(x[:n] for x in view))  # the states decided in within the limit
        candidates = th.as_tensor(np.stack(e["candidates"][:n]), device=model.device)
        q.append(th.stack(policy.critic(states, candidates.transpose(1, 2).float()), 0).min(0).values.cpu().numpy())
        if policy.actor_prior is not None:
            now, prior = policy.actor(states), policy.actor_prior(states)
            free = states.assignable
            kl.append(now.kl(prior)[free].cpu().numpy())
            changed.append((now.get_actions(True) != prior.get_actions(True))[free].cpu().numpy())
    qa, ga, gsa = np.concatenate(q), np.concatenate(g), np.concatenate(g_soft)
    figures.update(
        q_mean=float(qa.mean()),
        mc_return_mean=float(ga.mean()),
        q_corr=_corr(qa, ga),
        q_scale=float(qa @ ga / max(ga @ ga, 1e-12)),
        soft_return_mean=float(gsa.mean()),
        q_corr_soft=_corr(qa, gsa),
        entropy_bonus_mean=float(np.concatenate(bonus).mean()),
    )
    if kl:
        figures.update(kl_per_entity=float(np.concatenate(kl).mean()), argmax_changed=float(np.concatenate(changed).mean()))
    return figures
