"""What the critic and the actor of a TwoStageSAC model are doing, measured on rollouts of its own policy.

``python -m sb3_taskalloc.experiments diagnose --env RBF [--model PATH] [--steps N] [--episodes 3]`` reports (with a
plot of the critic against the expected return, of states and of decision pairs, where states were branched):

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
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import gymnasium as gym
import numpy as np
import torch as th

from sb3_taskalloc.baselines.greedy import COVER_TOL
from sb3_taskalloc.common.utils import atomic_write_text
from sb3_taskalloc.experiments.calibration import branch_calibration, critic_figures, unlimited_env
from sb3_taskalloc.two_stage_sac.updates import PreAssignUpdate


@dataclass
class Diagnosis:
    """The figures of :func:`diagnose` (NaN where a figure does not apply: the critic's without pre-assignment or with
    its actor held at its rule, whose critics do not train)."""

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
    advantage_ties: int = 0  # pairs whose branches all returned the same: left out of the same-sign share
    state_points: list[tuple[float, float]] = field(default_factory=list)  # (Q, Ḡ) of each branched state
    pair_points: list[tuple[float, float]] = field(default_factory=list)  # (ΔQ, ΔḠ) of each decision pair

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
                f"decision pairs ({self.advantage_pairs}, {self.advantage_ties} with equal returns): corr(ΔQ, ΔḠ); its "
                "ceiling; same sign, of the pairs whose returns differ",
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
    """One episode of the model's two-stage decisions: observations, candidate sets, kept tasks, env rewards,
    commitment rewards (``info["commitment_reward"]``, NaN where the env does not report it) and whether it ended by
    termination."""
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


@th.no_grad()
def diagnose(
    model: Any,
    env_id: str,
    episodes: int = 3,
    seed: int = 10_000,
    branches: int = 8,
    branch_stride: int = 10,
    progress: bool = False,
) -> Diagnosis:
    """Measure the model on ``episodes`` sampled and ``episodes`` deterministic episodes of ``env_id`` (seeds from
    ``seed``, disjoint from training seeds by default; ``seed`` also seeds the sampled decisions).

    :param model: a :class:`~sb3_taskalloc.TwoStageSAC`
    :param branches: rollouts per branched state of :func:`branch_calibration` (0: skip it)
    :param branch_stride: every ``branch_stride``-th state of an episode is branched
    :param progress: a progress bar over the branched episodes, the longest part
    """
    policy, gamma = model.policy, float(model.gamma)
    # The stage-1 critics train where a stage-1 update runs: where the pre-assign actor learns
    # (:func:`~sb3_taskalloc.two_stage_sac.updates.preassign_update`).
    critic = policy.critic is not None and any(isinstance(u, PreAssignUpdate) for u in getattr(model, "updates", ()))
    branches = branches if critic else 0
    alpha = float((th.exp(model.log_ent_coef) if model.log_ent_coef is not None else model.ent_coef_tensor).item())
    env = gym.make(env_id)
    long_env, limit = unlimited_env(env_id, gamma)
    cuda = [model.device.index or 0] if model.device.type == "cuda" else []
    with th.random.fork_rng(devices=cuda):  # the sampled decisions are reproducible and leave the caller's stream alone
        th.manual_seed(seed)
        sampled = [_episode(model, long_env, seed + k, deterministic=False) for k in range(episodes)]
        branched = (
            branch_calibration(model, env_id, [seed + k for k in range(episodes)], branches, branch_stride, progress)
            if branches
            else {}
        )
    deterministic = [_episode(model, env, seed + k, deterministic=True) for k in range(episodes)]
    nan = float("nan")
    figures: dict[str, Any] = dict(q_mean=nan, mc_return_mean=nan, q_corr=nan, q_scale=nan, soft_return_mean=nan)
    figures.update(q_corr_soft=nan, entropy_bonus_mean=nan, kl_per_entity=nan, argmax_changed=nan)
    within = slice(0, limit)  # the states and rewards of the episodes proper
    timing = getattr(model, "reward_timing", "completion")
    learned = "commitment" if timing == "commitment" else "rewards"  # the reward the stage-1 critic learns
    rewards = np.concatenate([e[learned][within] for e in sampled])
    if critic:
        figures.update(critic_figures(model, sampled, within, learned, alpha))
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


def write(diagnosis: Diagnosis, out: str | Path, command: str | None = None) -> Path:
    """``<out>/diagnose_<env>.json`` and ``.md``, and ``.png`` where states were branched (the critic against the
    expected return, of states and of decision pairs: :func:`.plots.plot_critic`); :return: the Markdown path.

    :param command: the command that measured it, written into both files
    """
    stem = Path(out) / f"diagnose_{diagnosis.env.split('/')[-1]}"
    record = asdict(diagnosis) | ({"command": command} if command else {})
    atomic_write_text(stem.with_suffix(".json"), json.dumps(record, indent=2) + "\n")
    if diagnosis.state_points:
        from sb3_taskalloc.experiments.plots import plot_critic

        d = diagnosis
        plot_critic(
            d.state_points,
            d.pair_points,
            stem.with_suffix(".png"),
            title=f"{d.env}: the stage-1 critic against the expected return Ḡ of {len(d.state_points)} branched states",
            labels=(f"corr {d.q_corr_expected:.2f}, scale {d.q_scale_expected:.2f}", _pair_label(d)),
        )
    text = diagnosis.table() + (f"\n\nCommand: `{command}`" if command else "")
    return atomic_write_text(stem.with_suffix(".md"), text + "\n")


def _pair_label(d: Diagnosis) -> str:
    if d.advantage_pairs < 2:
        return f"{d.advantage_pairs} pairs: too few to measure"
    sign = f"same sign {100 * d.advantage_sign:.0f} % of {d.advantage_pairs - d.advantage_ties}"
    return f"corr {d.advantage_corr:.2f}, ceiling {d.advantage_ceiling:.2f}, {sign}"
