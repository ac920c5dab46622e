"""A learned future value per entity in the exact pre-assignment (implementation detail 27): the per-step objective
plus what each entity it sends gives up, NeurADP's per-vehicle values added to the per-step ILP's coefficients.

Each entity's post-decision state has a linear value V = θ·[free, τ, e]: free is 1 if the decision leaves it
uncommitted, τ the steps until it is free again (the distance to its task's cell + 1, the observation's busy time; 0 if
free) and e the mean Manhattan distance from the cell where it will be free (its own, or its task's) to a uniform
cell of the grid, where tasks arrive. Sending entity i to task j gives up

    v_ij = V(i free) − V(i sent to j) = θ_free − θ_τ·(d_ij + 1) + θ_e·(e(cell_i) − e(cell_j)),

which :class:`EntityValueDecoder` adds to the pair's cost in the round's solve. θ is fitted by approximate policy
iteration with that decoder in the loop (:func:`fit_entity_values`): play episodes, regress the commitment return that
follows each decision on the post-decision Σ_i φ_i and controls for the time left, damp, repeat. For grid envs with
Manhattan travel (RBF); measured in docs/learning.md ("A learned per-robot value with the exact decoder in the loop").
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch as th

from sb3_taskalloc.common.torch_layers import ObsView
from sb3_taskalloc.common.utils import check_counts, check_finite
from sb3_taskalloc.two_stage_sac.decoding import Decoder, ExactTopDecoder, decide_pooled, register_decoder
from sb3_taskalloc.two_stage_sac.select_stage import Decision

if TYPE_CHECKING:
    from sb3_taskalloc.two_stage_sac.policies import TAMPolicy
    from sb3_taskalloc.two_stage_sac.two_stage_sac import TwoStageSAC

#: The controls of the regression (a constant and the time left, t/T and (t/T)²), the same for every decision of a
#: state, so they keep the time left in the episode from posing as an entity's value and no decoder needs them.
CONTROLS = 3


def cells(features: th.Tensor, n_resources: int) -> th.Tensor:
    """(…, 2) the grid cells of entities or tasks from their symlog features (cost or reward, K resources, x, y, …)."""
    return th.expm1(features[..., n_resources + 1 : n_resources + 3].double()).round()


def mean_distance(cell: th.Tensor, grid_size: int) -> th.Tensor:
    """(…) e: the mean Manhattan distance from ``cell`` (…, 2) to a uniform cell of the grid."""
    grid = th.arange(grid_size, dtype=th.float64, device=cell.device)
    return (cell.clamp(0, grid_size - 1).unsqueeze(-1) - grid).abs().mean(-1).sum(-1)


def pair_values(view: ObsView, theta: Sequence[float], grid_size: int) -> th.Tensor:
    """(B, N, M) v_ij, what sending entity i to task j gives up (module docstring), in the pair costs' dtype."""
    K = view.supply.shape[-1]
    here, there = cells(view.entity, K), cells(view.task, K)  # (B, N, 2), (B, M, 2)
    distance = (here.unsqueeze(2) - there.unsqueeze(1)).abs().sum(-1)
    moved = mean_distance(here, grid_size).unsqueeze(2) - mean_distance(there, grid_size).unsqueeze(1)
    values = theta[0] - theta[1] * (distance + 1.0) + theta[2] * moved  # float64 first, as the fit computed it
    return values.to(view.pair_cost.dtype)


def checked_theta(theta: Any, name: str) -> tuple[float, float, float]:
    """``theta`` as three floats (θ_free, θ_τ, θ_e), or a ValueError naming ``name`` if it is not three finite numbers."""
    real = int | float | np.integer | np.floating
    numbers = isinstance(theta, Sequence | np.ndarray) and all(isinstance(x, real) and np.isfinite(x) for x in theta)
    if not numbers or len(theta) != 3:
        raise ValueError(f"{name} must be three finite numbers (θ_free, θ_τ, θ_e), got {theta!r}")
    return (float(theta[0]), float(theta[1]), float(theta[2]))


class SelectValues(NamedTuple):
    """The select stage's pair costs with what committing each entity gives up: the pointer decodes (and is trained) on
    c_ij (1 + σ) + v_ij (``TAMPolicy(select_values=...)``, implementation detail 28), the costs that the recommended
    decoder solves on: :class:`EntityValueDecoder`'s learned values v_ij with θ (RBF), or ``exact_top``'s uniform
    surcharge σ (MT).

    :param theta: (θ_free, θ_τ, θ_e), e.g. the recommended decoder's (``settings.RECOMMENDED_DECODERS``); None: no v_ij
    :param grid_size: the grid's side, where tasks arrive at uniform cells (read with ``theta`` only)
    :param surcharge: σ ≥ 0, a uniform surcharge on every pair's cost
    """

    theta: tuple[float, float, float] | None = None
    grid_size: int = 7
    surcharge: float = 0.0

    @classmethod
    def of(cls, config: dict[str, Any] | None) -> SelectValues | None:
        """The values of a policy's ``select_values`` keyword (None: none), with a clear error for a bad one."""
        if config is None:
            return None
        keys = {"theta", "grid_size", "surcharge"}
        if not isinstance(config, dict) or not set(config) <= keys or not {"theta", "surcharge"} & set(config):
            raise ValueError(
                f"select_values must be None or a dict of 'theta' (with 'grid_size') and/or 'surcharge', got {config!r}"
            )
        theta = config.get("theta")
        theta = None if theta is None else checked_theta(theta, "select_values['theta']")
        grid_size = config.get("grid_size", 7)
        check_counts({"select_values['grid_size']": grid_size})
        surcharge = config.get("surcharge", 0.0)
        check_finite({"select_values['surcharge']": surcharge}, minimum=0.0, inclusive=True)
        return cls(theta, grid_size, float(surcharge))

    @property
    def config(self) -> dict[str, Any]:
        """The ``select_values`` keyword that rebuilds these values (what a saved model stores)."""
        config: dict[str, Any] = {} if self.theta is None else {"theta": list(self.theta), "grid_size": self.grid_size}
        return {**config, "surcharge": self.surcharge} if self.surcharge or self.theta is None else config

    def costed(self, view: ObsView) -> ObsView:
        """``view`` with each pair's cost raised by the surcharge and by what its entity gives up (:func:`pair_values`);
        :meth:`EntityValueDecoder.costed` reads the same."""
        cost = view.pair_cost + self.surcharge * view.pair_cost
        return view._replace(pair_cost=cost if self.theta is None else cost + pair_values(view, self.theta, self.grid_size))


@register_decoder
class EntityValueDecoder(ExactTopDecoder):
    """``exact_top`` whose pair costs also carry each entity's learned future value: the pair i → j costs
    c_ij (1 + σ) + v_ij in the round's solve and in weighing its teams (module docstring). With θ = 0 and σ = 0 it
    decides as ``exact_top`` of the same ``top``. θ comes from :func:`fit_entity_values`.

    :param top: each free entity's most probable tasks that the solve may pair it with
    :param theta: (θ_free, θ_τ, θ_e)
    :param grid_size: the grid's side, where tasks arrive at uniform cells
    :param surcharge: σ, a uniform surcharge on top (the fit's exploration draws one per decision)
    """

    name = "entity_value"

    def __init__(
        self, top: int = 2, theta: Sequence[float] = (0.0, 0.0, 0.0), grid_size: int = 7, surcharge: float = 0.0, seed: int = 0
    ) -> None:
        super().__init__(top=top, surcharge=surcharge, seed=seed)
        check_counts({"grid_size": grid_size})
        self.theta, self.grid_size = checked_theta(theta, "theta"), grid_size

    @property
    def config(self) -> dict[str, Any]:
        return {**super().config, "theta": self.theta, "grid_size": self.grid_size}

    @property
    def plain(self) -> bool:
        return super().plain and not any(self.theta)

    def costed(self, view: ObsView) -> ObsView:
        # The pointer's SelectValues compute these costs; built per call, as the fit's exploration sets the surcharge.
        return SelectValues(self.theta, self.grid_size, self.surcharge).costed(view)


@register_decoder
class PooledDecoder(Decoder):
    """No pre-assignment: the tasks pick in slot order from one shared pool of free entities, each its pointer's argmax
    team, and an abandoned task's picks return to the pool (:func:`.decoding.decide_pooled`, the "W/o Pre (sequence)"
    decision with the trained pointer), on pair costs that carry each entity's future value v_ij with this θ (module
    docstring) in place of the model's own (``select_values``; its surcharge stays), so that models trained with and
    without RBF's θ decide alike. Where entities are scarce, a pre-assignment that gives each entity one task splits
    them so that few tasks can be covered; one pool lets each task draw on every free entity, and v_ij keeps a task
    from spending robots that the next tasks need (RBF-EntityShift's recommended decoder: docs/learning.md, "One pool
    and RBF's per-robot values").

    :param theta: (θ_free, θ_τ, θ_e); all zero: the pointer's own costs, the model's values included
    :param grid_size: the grid's side, where tasks arrive at uniform cells
    """

    name = "pooled"

    def __init__(self, theta: Sequence[float] = (0.0, 0.0, 0.0), grid_size: int = 7, seed: int = 0) -> None:
        super().__init__(seed=seed)
        check_counts({"grid_size": grid_size})
        self.theta, self.grid_size = checked_theta(theta, "theta"), grid_size

    def decide(self, policy: TAMPolicy, view: ObsView, rounds_out: list[tuple[ObsView, th.Tensor]] | None = None) -> Decision:
        if rounds_out is not None:
            raise ValueError("the 'pooled' decoder has no pre-assign rounds to record (rounds_out)")
        costed = None  # θ = 0: the pointer's own costs (TAMPolicy.select_view)
        if any(self.theta):
            surcharge = 0.0 if policy.select_values is None else policy.select_values.surcharge
            costed = SelectValues(self.theta, self.grid_size, surcharge).costed(view)
        return decide_pooled(policy, view, deterministic=True, uniform=False, select_view=costed)


class EntityValueFit(NamedTuple):
    """What :func:`fit_entity_values` found: the decoder with the last θ, every θ (θ_0 = 0 first), each iteration's fit
    R² and its training episodes' mean return."""

    decoder: EntityValueDecoder
    thetas: list[tuple[float, ...]]
    r2: list[float]
    train_returns: list[float]


def post_decision(view: ObsView, env_action: np.ndarray, target: np.ndarray, grid_size: int) -> np.ndarray:
    """Σ over present entities of φ = [free, τ, e] after the decision ``env_action`` (N,) of one state ``view``
    (batch 1). ``target`` (N, 2) holds the cell of each committed entity's task, updated here with the sent ones'."""
    K = view.supply.shape[-1]
    M = view.task_mask.shape[1]
    here, there = cells(view.entity[0], K).cpu().numpy(), cells(view.task[0], K).cpu().numpy()
    busy_time = th.expm1(view.entity[0, :, K + 3].double()).round().cpu().numpy()  # distance to its task's cell + 1, or 0
    sent = (env_action < M) & view.entity_mask[0].cpu().numpy()
    target[sent] = there[env_action[sent]]
    tau = np.where(sent, np.abs(here - target).sum(-1) + 1.0, busy_time)
    busy = tau > 0
    cell = np.where(busy[:, None], target, here)
    e = mean_distance(th.as_tensor(cell), grid_size).numpy()
    present = view.present[0].cpu().numpy()
    return np.array([(~busy & present).sum(), tau[present].sum(), e[present].sum()])


def regress(rows: np.ndarray, y: np.ndarray, ridge: float = 1e-3) -> tuple[np.ndarray, float]:
    """θ of the post-decision features (the first columns of ``rows``; the last :data:`CONTROLS` are a constant and the
    time left) by ridge regression of ``y`` on standardised columns, and the fit's R²."""
    n = rows.shape[1] - CONTROLS
    mu, sd = rows.mean(0), rows.std(0) + 1e-8
    sd[n], mu[n] = 1.0, 0.0  # the constant column stays as it is
    z = (rows - mu) / sd
    w = np.linalg.solve(z.T @ z + ridge * len(z) * np.eye(z.shape[1]), z.T @ (y - y.mean()))
    residual = y - y.mean() - z @ w
    residual -= residual.mean()
    return (w / sd)[:n], float(1.0 - (residual**2).sum() / ((y - y.mean()) ** 2).sum())


class Exploration(NamedTuple):
    """A per-decision surcharge ξ ~ U(0, ``high``) from ``rng``."""

    rng: np.random.Generator
    high: float


def play(
    model: TwoStageSAC, env: Any, decoder: EntityValueDecoder, reset_seed: int, explore: Exploration | None = None
) -> tuple[float, np.ndarray, np.ndarray]:
    """One episode decided by ``decoder``: its return, each decision's post-decision features and controls (rows of
    the regression) and the commitment return that follows each decision.

    :param explore: the surcharge each decision adds (None: none)
    """
    obs, _ = env.reset(seed=reset_seed)
    horizon = float(env.spec.max_episode_steps)
    target = np.zeros((obs["entity_mask"].shape[0], 2))
    rows, commitments, total, done, t = [], [], 0.0, False, 0
    with model.decoding(decoder):
        while not done:
            if explore is not None:
                decoder.surcharge = float(explore.rng.uniform(0.0, explore.high))
            action = model.predict(obs, deterministic=True)[0]
            view = model.policy.parse(model.policy.obs_to_tensor(obs)[0])  # type: ignore[attr-defined]
            phi = post_decision(view, np.asarray(action), target, decoder.grid_size)
            rows.append(np.concatenate([phi, [1.0, t / horizon, (t / horizon) ** 2]]))
            obs, reward, terminated, truncated, info = env.step(action)
            commitments.append(float(info["commitment_reward"]))
            total += float(reward)
            done, t = terminated or truncated, t + 1
    after = np.concatenate([np.cumsum(commitments[::-1])[::-1][1:], [0.0]])  # what the later decisions commit
    return total, np.asarray(rows), after


def fit_entity_values(
    model: TwoStageSAC,
    env_id: str,
    iterations: int = 2,
    episodes: int = 8,
    explore: float = 0.2,
    damping: float = 0.5,
    top: int = 2,
    reset_seed: int = 60_000,
    seed: int = 0,
    env_kwargs: dict[str, Any] | None = None,
    progress_bar: bool = False,
) -> EntityValueFit:
    """θ of :class:`EntityValueDecoder` by approximate policy iteration with the decoder in the loop (implementation
    detail 27), from θ = 0 (``exact_top`` itself).

    Iteration k plays ``episodes`` episodes (reset seeds ``reset_seed + 100·k + e``; keep them apart from evaluation
    episodes) whose decisions add a surcharge ξ ~ U(0, ``explore``) drawn afresh at each (NeurADP's exploration by
    noise on the solver's coefficients: on-policy the entities a decision keeps and their later return hardly vary),
    regresses the commitment return after each decision on the post-decision Σ φ with the controls, and moves θ to
    (1 − ``damping``)·θ + ``damping``·fit (the first fit whole). The measured setting: RBF, 2 iterations of 8 episodes
    (docs/learning.md); each RBF episode takes about 20 s on one CPU thread. Ctrl-C returns the θ of the iterations
    done, with a warning (before the first ends, it raises KeyboardInterrupt).

    :param model: its policy prunes each entity's pairs to its ``top`` most probable tasks
    :param env_id: a grid env with Manhattan travel (``grid_size``; ``info["commitment_reward"]``)
    :param iterations: rounds of play and fit
    :param episodes: episodes per iteration; on RBF 16 narrowed the spread of the fits' returns over seeds (std 3.6
        against 9.6) at twice the time, with a mean gain inside the spread (docs/learning.md, "episodes per iteration")
    :param explore: the upper end of the per-decision surcharge ξ (0: none)
    :param damping: the weight of each new fit in θ after the first, in (0, 1]
    :param top: each entity's most probable tasks the solve considers
    :param reset_seed: the first training episode's reset seed
    :param seed: seeds the exploration's draws
    :param env_kwargs: keyword arguments of ``gym.make(env_id)``
    :param progress_bar: a progress bar over the episodes
    :return: the decoder with the last θ, every θ, each iteration's R² and its training episodes' mean return
    """
    import gymnasium as gym
    from tqdm.rich import tqdm

    check_counts({"iterations": iterations, "episodes": episodes, "top": top})
    check_finite({"explore": explore}, inclusive=True)
    check_finite({"damping": damping})
    if damping > 1:
        raise ValueError(f"damping must be in (0, 1], got {damping}")
    env = gym.make(env_id, **(env_kwargs or {}))
    travel, grid_size = getattr(env.unwrapped, "travel", None), getattr(env.unwrapped, "grid_size", None)
    if travel != "manhattan" or grid_size is None or env.spec is None or env.spec.max_episode_steps is None:
        raise ValueError(
            f"entity values need a grid env with Manhattan travel and a time limit (max_episode_steps): {env_id!r} has "
            f"travel={travel!r}, grid_size={grid_size!r}"
        )
    theta = np.zeros(3)
    thetas, r2s, train_returns = [tuple(float(x) for x in theta)], [], []
    bar = tqdm(total=iterations * episodes, disable=not progress_bar, desc="entity values")
    try:
        for k in range(iterations):
            decoder, rows, y, returns = EntityValueDecoder(top, theta.tolist(), grid_size), [], [], []
            for e in range(episodes):
                explorer = Exploration(np.random.default_rng([seed, k, e]), explore)
                total, episode_rows, after = play(model, env, decoder, reset_seed + 100 * k + e, explorer)
                rows.append(episode_rows)
                y.append(after)
                returns.append(total)
                bar.update()
            fitted, r2 = regress(np.concatenate(rows), np.concatenate(y))
            theta = fitted if k == 0 else (1.0 - damping) * theta + damping * fitted
            thetas.append(tuple(float(x) for x in theta))
            r2s.append(r2)
            train_returns.append(float(np.mean(returns)))
    except KeyboardInterrupt:
        if len(thetas) == 1:  # no iteration ended: there is no fit to keep
            raise
        # Minutes of episodes are in the iterations done: keep them, as Ctrl-C during DAgger keeps its iterations.
        warnings.warn(
            f"fit_entity_values interrupted after {len(thetas) - 1} of {iterations} iterations; it returns their θ",
            stacklevel=2,
        )
    finally:
        bar.close()
    return EntityValueFit(EntityValueDecoder(top, list(thetas[-1]), grid_size), thetas, r2s, train_returns)
