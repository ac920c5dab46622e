"""One gradient step of each stage of :class:`~sb3_taskalloc.TwoStageSAC`, in SAC's order: target → critic → actor →
temperature (the target networks follow in ``train``). The algorithm holds one update per stage it trains
(:func:`preassign_update` chooses stage 1's): none for the pre-assignment of a policy without it ("W/o Pre") or where
the pre-assign actor is held at its rule (``train_preassign_actor=False``).

Equations and numbers refer to the paper and to the implementation details of :mod:`sb3_taskalloc.two_stage_sac`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple

import torch as th
from torch.nn import functional as F

import sb3_taskalloc.two_stage_sac.losses as losses
from sb3_taskalloc.common.buffers import TwoStageReplayBufferSamples
from sb3_taskalloc.common.policies import CriticContext
from sb3_taskalloc.common.torch_layers import ObsView
from sb3_taskalloc.common.utils import (
    DivergenceError,
    check_finite_parameters,
    foreach_polyak_update,
)

if TYPE_CHECKING:
    from sb3_taskalloc.two_stage_sac.two_stage_sac import TwoStageSAC

#: Each logged value of the gradient steps of one ``train`` call, a detached tensor: the host reads them all at once at the
#: end of the call (:func:`read_logs`), not once per value, which on CUDA would wait for the GPU each time.
Logs = dict[str, list[th.Tensor]]


def entropy_coefficient(
    spec: str | float, name: str, device: th.device, lr: float
) -> tuple[th.Tensor | None, th.optim.Optimizer | None, th.Tensor | None]:
    """(log α parameter, its Adam optimizer at ``lr``, None) for ``"auto[_init]"``, or (None, None, α) for a float ≥ 0.

    :param name: the setting's name, for the error message
    """
    if isinstance(spec, str):
        head, _, init_text = spec.partition("_")
        try:
            init = float(init_text) if init_text else 0.1
        except ValueError:
            init = math.nan
        if head != "auto" or not math.isfinite(init):
            raise ValueError(f"{name} must be 'auto', 'auto_<initial value>' or a float, got {spec!r}")
        if init <= 0:
            raise ValueError(f"the initial value of {name} must be > 0, got {init}")
        log_alpha = th.log(th.ones(1, device=device) * init).requires_grad_(True)
        return log_alpha, th.optim.Adam([log_alpha], lr=lr), None
    if not (isinstance(spec, int | float) and math.isfinite(spec) and spec >= 0):
        raise ValueError(f"{name} must be 'auto', 'auto_<initial value>' or a float >= 0, got {spec!r}")
    return None, None, th.tensor(float(spec), device=device)


def temperature(log_alpha: th.Tensor | None, fixed: th.Tensor | None) -> th.Tensor:
    """α as a constant of this gradient step: exp(log α) when tuned, else the fixed value."""
    return th.exp(log_alpha.detach()) if log_alpha is not None else fixed  # type: ignore[return-value]


def optimizer_step(optimizer: th.optim.Optimizer, loss: th.Tensor) -> th.Tensor:
    """One step of ``optimizer`` on ``loss``; returns its value (detached)."""
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    return loss.detach()


def optimizers(model: TwoStageSAC) -> list[th.optim.Optimizer]:
    """Every optimizer a gradient step may run: the select stage's, the pre-assign stage's where the policy has one,
    and the tuned temperatures' (the learning-rate schedule sets all of them, as in SB3's SAC)."""
    found = (
        model.selector.optimizer,
        model.select_critic.optimizer,
        None if model.actor is None else model.actor.optimizer,
        None if model.critic is None else model.critic.optimizer,
        model.ent_coef_optimizer,
        model.select_ent_coef_optimizer,
    )
    return [optimizer for optimizer in found if optimizer is not None]


def read_logs(model: TwoStageSAC, logs: Logs, gradient_steps: int) -> dict[str, list[float]]:
    """The logged values of ``gradient_steps`` steps, read on the host in one transfer. Divergence is an error: a
    non-finite loss or temperature stops training, naming it and the steps it happened in."""
    keys = list(logs)
    flat = th.stack([v.reshape(()).float() for key in keys for v in logs[key]]).cpu().tolist() if keys else []
    read, start = {}, 0
    for key in keys:
        read[key], start = flat[start : start + len(logs[key])], start + len(logs[key])
        bad = [v for v in read[key] if not math.isfinite(v)]
        if bad:
            first, last = model._n_updates + 1, model._n_updates + gradient_steps
            steps = f"at gradient step {last}" if first == last else f"in gradient steps {first}–{last}"
            raise DivergenceError(
                f"training diverged {steps} (env step {model.num_timesteps}): {key} = {bad[0]}; lower the learning "
                f"rate ({model.learning_rate!r})"
            )
    return read


def check_parameters(model: TwoStageSAC) -> None:
    """Divergence is an error: a non-finite parameter of a trained network stops training, naming it."""
    modules = {"actor": model.actor, "critic": model.critic, "selector": model.selector, "select_critic": model.select_critic}
    check_finite_parameters(modules, f"by gradient step {model._n_updates} (env step {model.num_timesteps})")


class PreAssignCriticLoss(NamedTuple):
    loss: th.Tensor  # ½ Σ_k MSE(Q^k_tot(s, c), y)
    target_q: th.Tensor  # (B,) y
    current: tuple[th.Tensor, ...]  # (B,) Q^k_tot(s, c) of each critic k
    contexts: list[CriticContext]  # the online critics' action-independent parts on s (reused by the actor loss)


class PreAssignUpdate:
    """Stage 1, the pre-assignment (paper: Pre-assign Module, Algorithm 2): the TAM critics mixed by AMIX, the TAM actor
    and its temperature α.

    :param model: the algorithm, whose networks and settings are read at each step
    :param padded: the losses laid out with fixed shapes and no host read (the temperature's statistics weighted, not
        selected), as a CUDA graph records them (:mod:`.graph_step`)
    """

    def __init__(self, model: TwoStageSAC, padded: bool = False) -> None:
        self.model, self.padded = model, padded

    def critic_loss(
        self, obs: ObsView, next_obs: ObsView, data: TwoStageReplayBufferSamples, alpha: th.Tensor
    ) -> PreAssignCriticLoss:
        """The paper's L_critic(φ) in its soft form on the stored pre-assignment c (details 2–3)."""
        m = self.model
        assert m.actor is not None and m.critic is not None and m.critic_target is not None
        rewards, dones = data.rewards.squeeze(-1), data.dones.squeeze(-1)
        gamma = m.gamma if data.discounts is None else data.discounts.squeeze(-1)  # γ^k of an n-step return
        per_entity = m.entropy_bonus == "mean"
        # y = r + γ(1 − terminated)·[min_k AMIX̄^k(Σ_j π_i(j|s′)·Q̄^k_i(s′, j)) + α·H(s′)]
        with th.no_grad():
            next_dist = m.actor(next_obs)
            next_q = th.stack(m.critic_target(next_obs, next_dist.probs), dim=0).min(0).values
            next_v = next_q + alpha * losses.state_entropy(next_dist, next_obs, per_entity)
            target_q = rewards + (1 - dones) * gamma * next_v
        # ½ Σ_k (AMIX^k(Q^k_i(s, c_i)) − y)²
        contexts = m.critic.contexts(obs)
        current = m.critic.mix(contexts, data.candidates.transpose(1, 2).float())  # c one-hot: (B, N, M)
        loss = 0.5 * sum(F.mse_loss(q, target_q) for q in current)
        return PreAssignCriticLoss(loss, target_q, tuple(current), contexts)  # type: ignore[arg-type]

    def __call__(self, obs: ObsView, data: TwoStageReplayBufferSamples, logs: Logs) -> None:
        m = self.model
        assert m.actor is not None and m.critic is not None
        alpha = temperature(m.log_ent_coef, m.ent_coef_tensor)
        logs["ent_coef"].append(alpha.detach())
        # Target and critic.
        critic = self.critic_loss(obs, m.policy.parse(data.next_observations), data, alpha)
        logs["critic_loss"].append(critic.loss.detach())
        # Actor: −α·H(s) − min_k AMIX^k(Σ_j π_i(j|s) Q^k_i(s, j)) on the critic values above (detail 3), + β·KL(π ‖ π₀)
        # (detail 12). The parameters are disjoint, so one backward pass gives each network its own gradient.
        dist = m.actor(obs)
        actor_loss = losses.preassign_actor_loss(
            dist, m.critic, critic.contexts, obs, alpha, m.policy.actor_prior, m.prior_coef, m.entropy_bonus == "mean"
        )
        logs["actor_loss"].append(actor_loss.detach())
        m.critic.optimizer.zero_grad()
        m.actor.optimizer.zero_grad()
        (critic.loss + actor_loss).backward()
        m.critic.optimizer.step()
        m.actor.optimizer.step()
        # Temperature: log α·(H̄ − H̄*) on the mean per-entity entropy (detail 4).
        if m.log_ent_coef is not None and m.ent_coef_optimizer is not None:
            entropy = losses.preassign_entropy(dist, obs, m.target_entropy_ratio, weighted=self.padded)
            if self.padded or entropy.entropy.numel() > 0:  # padded: a batch with no free entity weighs 0
                ent_loss = losses.ent_coef_loss(m.log_ent_coef, entropy.entropy, entropy.target, entropy.weight)
                logs["ent_coef_loss"].append(optimizer_step(m.ent_coef_optimizer, ent_loss))

    def update_target(self) -> None:
        m = self.model
        assert m.critic is not None and m.critic_target is not None
        foreach_polyak_update(m.critic.parameters(), m.critic_target.parameters(), m.tau)


def preassign_update(model: TwoStageSAC) -> PreAssignUpdate | None:
    """Stage 1's update: the paper's (AMIX critics, actor, temperature) where the pre-assign actor learns; none
    otherwise ("W/o Pre", or a held actor whose AMIX critics no decision reads: detail 23)."""
    if model.actor is None:
        return None
    return PreAssignUpdate(model) if model.train_preassign_actor else None


class SelectUpdate:
    """Stage 2, the select stage (paper: Select Module, Algorithm 3): discrete SAC on the stored pick orders (detail 5)
    on the first ``select_kwargs["batch_size"]`` rows of the minibatch (each holds up to M × team-size transitions),
    plus the team-search distillation term (detail 18) when its weight is positive.

    :param model: the algorithm, whose networks and settings are read at each step
    :param padded: every round laid out with N pick steps and the transitions weighted, the team search decoded by the
        fixed-length loop: the same losses up to rounding, with fixed shapes and no host read, as a CUDA graph records
        them (:mod:`.graph_step`)
    """

    def __init__(self, model: TwoStageSAC, padded: bool = False) -> None:
        self.model, self.padded = model, padded

    def __call__(self, obs: ObsView, data: TwoStageReplayBufferSamples, logs: Logs) -> None:
        m, cfg = self.model, self.model.select_kwargs
        steps = obs.entity.shape[1] if self.padded else None  # N pick steps always suffice
        alpha = temperature(m.log_select_ent_coef, m.select_ent_coef_tensor)
        logs["select_ent_coef"].append(alpha.detach())
        rows = slice(0, cfg["batch_size"])
        view = m.policy.select_view(ObsView(*(x[rows] for x in obs)))  # the pointer's own costs
        candidates = data.candidates[rows]
        # Target Q^k(s_t, a_t) → r_t + (1 − done_t)·Σ_a π(a|s_{t+1})[min_k Q̄^k(s_{t+1}, a) − α_s log π(a|s_{t+1})]
        # (γ = 1 within a task), the critic loss on it, and the actor loss Σ_a π(a|s_t)[α_s log π(a|s_t) − min_k Q^k(s_t, a)]
        # + β_s·KL(π ‖ π₀), all steps of all tasks teacher-forced in one pass.
        select = losses.select_losses(
            m.selector,
            m.select_critic,
            m.select_critic_target,
            view,
            candidates,
            data.pick_rank[rows],
            m.policy.preassign,
            alpha,
            m.target_entropy_ratio,
            m.policy.selector_prior,
            cfg["prior_coef"],
            steps,
        )
        if select is None:  # no task picked anything in these rows
            return
        logs["select_critic_loss"].append(optimizer_step(m.select_critic.optimizer, select.critic_loss))
        actor_loss = select.actor_loss
        if cfg["search_coef"] > 0:  # each row costs search_samples decodes of every task
            found = losses.select_search_loss(
                m.selector, view, candidates, cfg["search_samples"], cfg["search_temperature"], steps
            )
            logs["select_search_loss"].append(found.loss.detach())
            logs["select_search_improved"].append(found.improved)
            logs["select_search_gain"].append(found.gain)
            actor_loss = actor_loss + cfg["search_coef"] * found.loss
        logs["select_actor_loss"].append(optimizer_step(m.selector.optimizer, actor_loss))
        if m.log_select_ent_coef is not None and m.select_ent_coef_optimizer is not None:
            ent_loss = losses.ent_coef_loss(m.log_select_ent_coef, select.entropy, select.target_entropy, select.weight)
            logs["select_ent_coef_loss"].append(optimizer_step(m.select_ent_coef_optimizer, ent_loss))

    def update_target(self) -> None:
        m = self.model
        foreach_polyak_update(m.select_critic.parameters(), m.select_critic_target.parameters(), m.tau)
