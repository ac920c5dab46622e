"""What the critic and the actor of a TwoStageSAC model are doing, measured on rollouts of its own policy.

``python -m sb3_taskalloc.experiments diagnose --env RBF [--model PATH] [--steps N] [--episodes 3]`` reports:

- critic calibration: on the states of sampled episodes, the correlation and the scale ratio (least-squares slope
  through the origin) of Q(s, c) = min_k AMIX^k(Q^k_i(s, c_i)) for the executed pre-assignment c against the
  Monte-Carlo discounted return G_t = Σ_k γ^k r_{t+k}, and against the entropy-inclusive return that the soft target
  bootstraps, G^H_t = Σ_k γ^k (r_{t+k} + γ α H(s_{t+k+1})). The critic bootstraps through the time limit (it does
  not observe time), so the returns are summed over a rollout that runs past the limit until the discount has spent
  99 % of its weight; only the states within the limit are compared. Cut at the limit, G_t would fall to 0 near the end
  of every episode, and the correlation would measure that fall instead of the critic. r is the reward the critic
  learns: the env reward, or ``info["commitment_reward"]`` for a model trained with ``reward_timing="commitment"``
  (the same profit, credited when a team is committed instead of when it arrives: on MT about 24 steps earlier, a
  factor 0.9^24 ≈ 0.08 at γ = 0.9, so the env reward would misjudge such a critic);
- the critic against the expected return (:func:`branch_calibration`): from every ``branch_stride``-th state of
  further sampled episodes, ``branches`` rollouts that share the executed step and differ in the env's randomness (the
  arrivals, the demand noise) and in the sampled decisions after it. Their mean Ḡ estimates E[G | s, c], the quantity
  Q(s, c) estimates; corr(Q, Ḡ) is the critic's calibration without the noise of one rollout, and the return ceiling
  sqrt(Var E[G|s,c] / Var G) is the correlation with one-rollout returns that a perfect critic would reach (the noise
  bound of corr(Q, G)). The correlations of Q and of Ḡ with the number of free entities show a critic that values
  free entities the returns do not;
- the critic's preferences between decisions, what the actor's gradient follows (:func:`advantage_figures`): at each
  branched state a second sampled pre-assignment c′ (where it differs from c) is branched with the same env seeds, and
  the difference Q(s, c) − Q(s, c′) is compared with the paired difference of the branch returns ΔḠ. A critic whose
  state values track Ḡ can still rank the decisions of one state at random: state values vary with the time and the
  free entities, the advantages between decisions are much smaller;
- the entropy bonus of the stage-1 target against the reward: mean γ·α·H(s') and mean |r| per transition;
- the actor against its initial rule: KL(π ‖ π₀) per free entity and the share of free entities whose argmax task
  changed;
- sampled against deterministic return, on the same evaluation seeds;
- which stage's learning the deterministic return owes to: the return with the pre-assign actor learned and the pointer
  at its initial rule, and the other way round (:func:`stage_returns`). Each stage learns against the other's current
  behaviour, so the two gains need not add up; a stage whose swap scores above the model is one whose learning hurts;
- what becomes of the open tasks in the deterministic episodes (:func:`task_outcomes`): the shares of open tasks per
  step whose team is kept, whose candidates fall short of the demand, whose candidates cover it without profit, and
  that have no candidates. A per-entity pre-assignment that leaves most open tasks short or empty is where a
  per-step optimum such as the MILP gains.
"""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal, SupportsFloat

import gymnasium as gym
import numpy as np
import torch as th

from sb3_taskalloc.baselines.greedy import COVER_TOL
from sb3_taskalloc.common.torch_layers import ObsView
from sb3_taskalloc.common.utils import atomic_write_text
from sb3_taskalloc.two_stage_sac.losses import state_entropy


@dataclass
class Diagnosis:
    """The figures of :func:`diagnose` (NaN where a figure does not apply, e.g. without pre-assignment)."""

    env: str
    episodes: int
    gamma: float
    reward_timing: str
    ent_coef: float
    sampled_return: float
    deterministic_return: float
    actor_only_return: float
    pointer_only_return: float
    q_mean: float
    mc_return_mean: float
    q_corr: float
    q_scale: float
    soft_return_mean: float
    q_corr_soft: float
    entropy_bonus_mean: float
    abs_reward_mean: float
    kl_per_entity: float
    argmax_changed: float
    tasks_kept: float
    tasks_short: float
    tasks_unprofitable: float
    tasks_no_candidates: float
    branch_states: int = 0
    q_corr_expected: float = math.nan
    q_scale_expected: float = math.nan
    return_ceiling: float = math.nan
    free_corr_q: float = math.nan
    free_corr_expected: float = math.nan
    advantage_pairs: int = 0
    advantage_corr: float = math.nan
    advantage_ceiling: float = math.nan
    advantage_sign: float = math.nan

    def table(self) -> str:
        """A Markdown table of the figures."""
        rows = [
            ("return, sampled / deterministic", f"{self.sampled_return:.2f} / {self.deterministic_return:.2f}"),
            (
                "deterministic return, only the pre-assign actor learned / only the pointer learned",
                f"{self.actor_only_return:.2f} / {self.pointer_only_return:.2f}",
            ),
            ("critic Q, mean", f"{self.q_mean:.3f}"),
            ("Monte-Carlo return G, mean", f"{self.mc_return_mean:.3f}"),
            ("corr(Q, G), scale Q/G", f"{self.q_corr:.3f}, {self.q_scale:.3f}"),
            (
                f"expected return Ḡ ({self.branch_states} states): corr(Q, Ḡ), scale Q/Ḡ; ceiling of corr(Q, G)",
                f"{self.q_corr_expected:.3f}, {self.q_scale_expected:.3f}; {self.return_ceiling:.3f}",
            ),
            ("corr with the number of free entities: Q / Ḡ", f"{self.free_corr_q:.3f} / {self.free_corr_expected:.3f}"),
            (
                f"decision pairs ({self.advantage_pairs}): corr(ΔQ, ΔḠ); its ceiling; same sign",
                f"{self.advantage_corr:.3f}; {self.advantage_ceiling:.3f}; {100 * self.advantage_sign:.1f} %",
            ),
            ("entropy-inclusive return G^H, mean; corr(Q, G^H)", f"{self.soft_return_mean:.3f}, {self.q_corr_soft:.3f}"),
            ("γ·α·H(s') per transition / mean |r|", f"{self.entropy_bonus_mean:.3f} / {self.abs_reward_mean:.3f}"),
            ("KL(π ‖ π₀) per free entity", f"{self.kl_per_entity:.2e}"),
            ("free entities whose argmax task changed", f"{100 * self.argmax_changed:.1f} %"),
            (
                "open tasks per step (deterministic): kept / short of demand / unprofitable / no candidates",
                " / ".join(
                    f"{100 * v:.1f} %"
                    for v in (self.tasks_kept, self.tasks_short, self.tasks_unprofitable, self.tasks_no_candidates)
                ),
            ),
        ]
        head = f"{self.env}: {self.episodes} sampled and {self.episodes} deterministic episodes"
        head += f", γ {self.gamma}, α {self.ent_coef:.4g}, the critic's reward r credited at {self.reward_timing}"
        return "\n".join([head, "", "| figure | value |", "|---|---|", *(f"| {k} | {v} |" for k, v in rows)])


def _episode(model: Any, env: gym.Env, seed: int, deterministic: bool) -> dict[str, Any]:
    """One episode of the model's two-stage decisions: observations, candidate sets, env rewards, commitment rewards
    (``info["commitment_reward"]``, NaN where the env does not report it) and whether it ended by termination."""
    policy = model.policy
    obs, _ = env.reset(seed=seed)
    observations, candidates, kept, rewards, credits = [], [], [], [], []
    done = False
    while not done:
        with th.inference_mode():
            view = policy.parse(policy.obs_to_tensor(obs)[0])
            decision = policy.decide(view, deterministic=deterministic)
        observations.append(obs)
        candidates.append(decision.candidates[0].cpu().numpy())
        kept.append(decision.kept[0].cpu().numpy())
        obs, reward, terminated, truncated, info = env.step(decision.env_action[0].cpu().numpy())
        rewards.append(float(reward))
        credits.append(float(info.get("commitment_reward", math.nan)))
        done = terminated or truncated
    observations.append(obs)
    return {
        "obs": observations,
        "candidates": candidates,
        "kept": kept,
        "rewards": np.asarray(rewards),
        "commitment": np.asarray(credits),
        "terminated": terminated,
    }


@contextmanager
def stage_reset(policy: Any, stage: Literal["actor", "selector"]) -> Iterator[None]:
    """Within the block, ``policy``'s pre-assign actor or pointer (``stage``) is back at its initial rule (the frozen
    prior π₀ of implementation detail 12); its learned weights return on leaving."""
    module = getattr(policy, stage)
    saved = copy.deepcopy(module.state_dict())
    module.load_state_dict(getattr(policy, f"{stage}_prior").state_dict())
    try:
        yield
    finally:
        module.load_state_dict(saved)


def stage_returns(model: Any, env_id: str, seeds: list[int]) -> dict[str, list[float]]:
    """Deterministic returns on ``seeds`` with one stage at its initial rule: ``"actor_only"`` (pre-assign actor
    learned, pointer initial) and ``"pointer_only"`` (the other way round); empty without a pre-assign actor."""
    if model.policy.actor is None or model.policy.actor_prior is None:
        return {}
    env = gym.make(env_id)
    out = {}
    for column, reset in (("actor_only", "selector"), ("pointer_only", "actor")):
        with stage_reset(model.policy, reset):  # type: ignore[arg-type]
            out[column] = [float(_episode(model, env, s, deterministic=True)["rewards"].sum()) for s in seeds]
    return out


def task_outcomes(obs: dict[str, np.ndarray], candidates: np.ndarray, kept: np.ndarray, tol: float = COVER_TOL) -> np.ndarray:
    """Counts of the open tasks of one decision by outcome: [kept, short of demand, covered without profit, no
    candidates].

    :param obs: the observation decided on
    :param candidates: (M, N) bool candidate sets of the decision
    :param kept: (M,) bool tasks whose team was kept
    :param tol: demand left below this counts as covered (Greedy's tolerance)
    """
    open_ = obs["task_mask"].astype(bool)
    has = candidates.any(1)
    supply = candidates.astype(np.float64) @ obs["entity_supply"].astype(np.float64)  # (M, K) candidates' total supply
    short = (supply < obs["task_demand"] - tol).any(1)
    outcomes = [kept, ~kept & has & short, ~kept & has & ~short, ~kept & ~has]
    return np.array([int((o & open_).sum()) for o in outcomes])


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


def _long_env(env_id: str, gamma: float) -> tuple[gym.Env, int | None]:
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
def branch_calibration(model: Any, env_id: str, seeds: list[int], branches: int = 8, stride: int = 10) -> dict[str, Any]:
    """The critic against the expected return (see the module docstring): the figures ``branch_states``,
    ``q_corr_expected``, ``q_scale_expected``, ``return_ceiling``, ``free_corr_q`` and ``free_corr_expected`` of
    :class:`Diagnosis`, and the ``advantage_*`` figures of :func:`advantage_figures`, measured on sampled episodes with
    reset seeds ``seeds`` (NaN without a pre-assign critic).

    :param branches: rollouts per state (≥ 2: the ceiling needs their spread)
    :param stride: every ``stride``-th state of an episode is branched
    """
    if branches < 2 or stride < 1:
        raise ValueError(f"branches must be >= 2 and stride >= 1, got {branches} and {stride}")
    policy, gamma = model.policy, float(model.gamma)
    nan = float("nan")
    out: dict[str, Any] = dict(branch_states=0, q_corr_expected=nan, q_scale_expected=nan, return_ceiling=nan)
    out.update(free_corr_q=nan, free_corr_expected=nan, advantage_pairs=0, advantage_corr=nan, advantage_ceiling=nan)
    out.update(advantage_sign=nan)
    if policy.actor is None or policy.critic is None:
        return out
    env, limit = _long_env(env_id, gamma)
    cuda = [model.device.index or 0] if model.device.type == "cuda" else []
    q, returns, free, gaps, gap_returns = [], [], [], [], []
    for s in seeds:
        obs, _ = env.reset(seed=s)
        for t in range(limit if limit is not None else 10**9):
            view = policy.parse(policy.obs_to_tensor(obs)[0])
            decision = policy.decide(view, deterministic=False)
            action = decision.env_action[0].cpu().numpy()
            if t % stride == 0 and bool(view.assignable.any()):
                key = 1_000 * s + t
                q_c = _critic_value(policy, view, decision.candidates)
                q.append(q_c)
                returns.append(_branch_returns(model, env, action, branches, _horizon(gamma), key=key))
                free.append(float(view.assignable.sum()))
                # The alternative draws from its own seeded stream: the figures above stay those of the stream alone.
                with th.random.fork_rng(devices=cuda):
                    th.manual_seed(key)
                    other = policy.decide(view, deterministic=False)
                    if not th.equal(other.candidates, decision.candidates):
                        alt = _branch_returns(model, env, other.env_action[0].cpu().numpy(), branches, _horizon(gamma), key)
                        gaps.append(q_c - _critic_value(policy, view, other.candidates))
                        gap_returns.append(returns[-1] - alt)
            obs, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                break
    if len(q) < 2:
        return {**out, "branch_states": len(q)}
    figures = calibration_figures(np.asarray(q), np.stack(returns), np.asarray(free))
    if len(gaps) >= 2:
        figures.update(advantage_figures(np.asarray(gaps), np.stack(gap_returns)))
    else:
        figures.update(advantage_pairs=len(gaps), advantage_corr=nan, advantage_ceiling=nan, advantage_sign=nan)
    return figures


def _critic_value(policy: Any, view: ObsView, candidates: th.Tensor) -> float:
    """Q(s, c) = min_k AMIX^k of one state and its candidate sets (1, M, N)."""
    return float(th.stack(policy.critic(view, candidates.transpose(1, 2).float()), 0).min(0).values.item())


def advantage_figures(gaps: np.ndarray, differences: np.ndarray) -> dict[str, Any]:
    """The critic's preference between two decisions of a state against the returns they lead to.

    With the branches of both decisions paired by their env seeds, d_k = G_k(c) − G_k(c′) = Δμ + ε_k. The paired means
    d̄ estimate Δμ = E[G|s,c] − E[G|s,c′] with noise Var(ε)/K, so a critic whose ΔQ equals Δμ correlates with d̄ by
    sqrt(Var Δμ / Var d̄): the ceiling of corr(ΔQ, ΔḠ). Same sign: the share of pairs whose ΔQ and d̄ agree in sign,
    i.e. where the critic prefers the decision whose branches did better.

    :param gaps: (P,) Q(s, c) − Q(s, c′) of the decision pairs
    :param differences: (P, K) the paired branch returns G_k(c) − G_k(c′)
    """
    if differences.ndim != 2 or differences.shape[1] < 2 or len(gaps) != len(differences):
        raise ValueError(f"need (P,) gaps and (P, K >= 2) paired differences, got {gaps.shape} and {differences.shape}")
    mean = differences.mean(1)
    noise = float(differences.var(1, ddof=1).mean()) / differences.shape[1]  # Var of a pair's mean around Δμ
    total = float(mean.var(ddof=1))
    return dict(
        advantage_pairs=len(gaps),
        advantage_corr=_corr(gaps, mean),
        advantage_ceiling=math.sqrt(max(total - noise, 0.0) / total) if total > 0 else float("nan"),
        advantage_sign=float(np.mean(np.sign(gaps) == np.sign(mean))),
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
def diagnose(
    model: Any, env_id: str, episodes: int = 3, seed: int = 10_000, branches: int = 8, branch_stride: int = 10
) -> Diagnosis:
    """Measure the model on ``episodes`` sampled and ``episodes`` deterministic episodes of ``env_id`` (seeds from
    ``seed``, disjoint from training seeds by default; ``seed`` also seeds the sampled decisions).

    :param model: a :class:`~sb3_taskalloc.TwoStageSAC`
    :param branches: rollouts per branched state of :func:`branch_calibration` (0: skip it)
    :param branch_stride: every ``branch_stride``-th state of an episode is branched
    """
    policy, gamma = model.policy, float(model.gamma)
    alpha = float((th.exp(model.log_ent_coef) if model.log_ent_coef is not None else model.ent_coef_tensor).item())
    env = gym.make(env_id)
    long_env, limit = _long_env(env_id, gamma)
    cuda = [model.device.index or 0] if model.device.type == "cuda" else []
    with th.random.fork_rng(devices=cuda):  # the sampled decisions are reproducible and leave the caller's stream alone
        th.manual_seed(seed)
        sampled = [_episode(model, long_env, seed + k, deterministic=False) for k in range(episodes)]
        branched = (
            branch_calibration(model, env_id, [seed + k for k in range(episodes)], branches, branch_stride) if branches else {}
        )
    deterministic = [_episode(model, env, seed + k, deterministic=True) for k in range(episodes)]
    nan = float("nan")
    figures: dict[str, Any] = dict(q_mean=nan, mc_return_mean=nan, q_corr=nan, q_scale=nan, soft_return_mean=nan)
    figures.update(q_corr_soft=nan, entropy_bonus_mean=nan, kl_per_entity=nan, argmax_changed=nan)
    within = slice(0, limit)  # the states and rewards of the episodes proper
    timing = getattr(model, "reward_timing", "completion")
    learned = "commitment" if timing == "commitment" else "rewards"  # the reward the stage-1 critic learns
    rewards = np.concatenate([e[learned][within] for e in sampled])
    if policy.actor is not None and policy.critic is not None:
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
            assign = th.as_tensor(np.stack(e["candidates"][:n]), device=model.device).transpose(1, 2).float()
            q.append(th.stack(policy.critic(states, assign), 0).min(0).values.cpu().numpy())
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
            figures.update(
                kl_per_entity=float(np.concatenate(kl).mean()), argmax_changed=float(np.concatenate(changed).mean())
            )
    stages = {k: float(np.mean(v)) for k, v in stage_returns(model, env_id, [seed + k for k in range(episodes)]).items()}
    decisions = [d for e in deterministic for d in zip(e["obs"][:-1], e["candidates"], e["kept"], strict=True)]
    counts = np.sum([task_outcomes(*d) for d in decisions], axis=0) if decisions else np.zeros(4)
    shares = counts / max(float(counts.sum()), 1.0)
    figures.update(zip(("tasks_kept", "tasks_short", "tasks_unprofitable", "tasks_no_candidates"), shares, strict=True))
    return Diagnosis(
        env=env_id,
        episodes=episodes,
        gamma=gamma,
        reward_timing=timing,
        ent_coef=alpha,
        sampled_return=float(np.mean([e["rewards"][within].sum() for e in sampled])),
        deterministic_return=float(np.mean([e["rewards"].sum() for e in deterministic])),
        actor_only_return=stages.get("actor_only", math.nan),
        pointer_only_return=stages.get("pointer_only", math.nan),
        abs_reward_mean=float(np.abs(rewards).mean()),
        **figures,
        **branched,
    )


def write(diagnosis: Diagnosis, out: str | Path) -> Path:
    """``<out>/diagnose_<env>.json`` and ``.md``; :return: the Markdown path."""
    stem = Path(out) / f"diagnose_{diagnosis.env.split('/')[-1]}"
    atomic_write_text(stem.with_suffix(".json"), json.dumps(asdict(diagnosis), indent=2) + "\n")
    return atomic_write_text(stem.with_suffix(".md"), diagnosis.table() + "\n")
