"""Shared engine of the task-allocation environments.

One vectorised NumPy implementation of the allocation mechanics; the four environments are this class
configured by data tables and keyword arguments (``envs/almighty.py``, ``ept.py``, ``rbf.py``, ``mt.py``).
"""

from __future__ import annotations

from typing import Any, ClassVar, Literal

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from envs.arrival import Arrival, make_arrival
from envs.dynamics import TaskAllocDynamics
from envs.geometry import Travel, static_tower_costs, travel_step
from envs.layout import ObsLayout
from envs.rendering import RenderSnapshot, render_ansi, render_rgb
from envs.tables import EntityTable, TaskTable, clone
from envs.validation import EPS, check_action, check_bids, check_config


class TaskAllocEnv(TaskAllocDynamics, gym.Env):
    """Dynamic multi-entity task allocation, padded and masked for variable entity and task counts.

    A manager repeatedly assigns free entities to open tasks. Each task needs a vector of resources and pays its
    reward once the entities committed to it cover that vector; each entity used costs money. The return is
    Σ over completed tasks of (reward − Σ pair costs of its team).

    ## Action Space

    ``MultiDiscrete([M + 1] * N)``: entry ``i`` is the task slot (``0..M-1``) entity ``i`` is assigned to, or ``M``
    for "unassigned". Assignments that break the mask (busy or absent entity, closed or empty task) are treated as
    "unassigned" and counted in ``info["invalid_assignments"]`` (``strict=True`` raises instead). Out-of-space actions
    (wrong shape, out of range, NaN, non-integer) raise ``ValueError``.

    ## Observation Space

    ``Dict`` padded to ``N = max_entities`` and ``M = max_tasks`` (K = number of resources):

    | key | shape | meaning |
    |---|---|---|
    | ``entity_features`` | (N, K + 5) | cost, supply (K), x, y, busy time (steps to arrival + 1, 0 if free), bid |
    | ``task_features`` | (M, K + 4) | reward, remaining demand (K), x, y, age |
    | ``entity_supply`` | (N, K) | resources each entity brings |
    | ``task_demand`` | (M, K) | demand not yet covered by the entities committed to the task |
    | ``task_reward`` | (M,) | reward paid on completion now (after decay) |
    | ``pair_cost`` | (N, M) | what entity i is charged if it is assigned to task j now |
    | ``entity_mask`` | (N,) | entity present and free to be assigned |
    | ``task_mask`` | (M,) | task present and open (demand not yet covered by committed entities) |
    | ``action_mask`` | (N·(M+1),) | sb3-contrib layout: per entity, M task choices then "unassigned" (always 1) |

    ## Rewards

    On completion of a task: its current reward minus the pair costs of every entity committed to it (the costs are
    fixed when the entity is assigned). No other reward. ``info`` carries ``completed_tasks``, ``task_reward_total``,
    ``cost_total``, ``invalid_assignments`` and ``entity_income`` (what each entity was paid this step).

    ``info["commitment_reward"]`` is the same return credited when it is earned rather than when it is paid: a task's
    current reward minus its team's charges in the step its committed entities cover it (it closes), then at
    completion the change of its reward since (the decay during travel), and at termination minus the credit of every
    closed task still unpaid. Its sum over a terminated episode equals the return; a learner can use it to credit a
    profit to the decision that earned it, steps before the team arrives (``TwoStageSAC(reward_timing="commitment")``).

    ## Starting State

    Entity table restored (positions at their start cells), tasks drawn by the arrival process.

    ## Episode End

    ``terminated`` when nothing more can happen (one-step envs after their step; the reference task list exhausted
    with every slot empty; every entity used up). Truncation by ``max_episode_steps`` at registration.

    ## Arguments

    :param entities: entity table (cost, supply, start positions, wire costs)
    :param tasks: table of tasks that can arrive (reward, demands; positions/towers for the reference schedule)
    :param max_entities: padded entity count N (>= number of entities; default: exactly the table)
    :param max_tasks: number of task slots M
    :param grid_size: side of the square grid (positions lie in ``0..grid_size-1``); None for no world
    :param travel: how committed entities move: ``"none"`` (work at once), ``"manhattan"`` (4-neighbour, y then x),
        ``"chebyshev"`` (8-neighbour)
    :param travel_cost: cost per unit of distance added to an entity's base cost (base + travel × distance)
    :param busy: whether committed entities stay committed until their task completes (False: EPT's towers)
    :param consume: whether an entity that completes a task is used up for the rest of the episode (MT's trucks)
    :param arrival: ``"random"`` (every ``arrival_period`` steps, ``arrival_count`` tasks drawn from the table at
        random positions, capped by free slots), ``"reference"`` (the table in order, refilling empty slots every
        period) or ``"static"`` (the whole table at reset, nothing later)
    :param arrival_period: steps between arrivals
    :param arrival_count: inclusive range of the number of tasks drawn per random arrival
    :param reward_scale: multiplier applied to task rewards and demands when a task arrives (EPT's peak factor 2)
    :param demand_noise: relative noise on open tasks' demands redrawn every step (EPT's changing peak demand)
    :param decay: factor ρ applied to the reward and the demand of tasks older than ``decay_after`` steps
    :param decay_after: age θ (steps) after which tasks decay
    :param decay_while_committed: whether a task keeps decaying once entities are committed to it (False: only
        tasks that nobody is travelling to or working on decay)
    :param one_step: the episode ends after the first step (Almighty)
    :param bidding: the entities' base costs are bids posted with :meth:`set_bids`
    :param bid_max: upper bound of a bid (default: 3 × the largest base cost)
    :param strict: raise ``ValueError`` on mask-violating assignments instead of counting them
    :param render_mode: ``"rgb_array"`` or ``"ansi"``
    """

    metadata: dict[str, Any] = {"render_modes": ["rgb_array", "ansi"], "render_fps": 4}  # noqa: RUF012

    def __init__(
        self,
        entities: EntityTable,
        tasks: TaskTable,
        max_entities: int | None = None,
        max_tasks: int = 10,
        grid_size: int | None = None,
        travel: Travel = "none",
        travel_cost: float = 0.0,
        busy: bool = True,
        consume: bool = False,
        arrival: Literal["random", "reference", "static"] = "random",
        arrival_period: int = 5,
        arrival_count: tuple[int, int] = (5, 10),
        reward_scale: float = 1.0,
        demand_noise: float = 0.0,
        decay: float = 1.0,
        decay_after: int = 10,
        decay_while_committed: bool = True,
        one_step: bool = False,
        bidding: bool = False,
        bid_max: float | None = None,
        strict: bool = False,
        render_mode: str | None = None,
    ) -> None:
        n = len(entities)
        self.n_entities = n
        self.max_entities = max_entities if max_entities is not None else n
        self.max_tasks = int(max_tasks)
        check_config(
            entities, tasks, self.metadata["render_modes"], max_entities=self.max_entities, max_tasks=self.max_tasks,
            grid_size=grid_size, travel=travel, travel_cost=travel_cost, arrival=arrival, arrival_period=arrival_period,
            arrival_count=arrival_count, reward_scale=reward_scale, demand_noise=demand_noise, decay=decay,
            decay_after=decay_after, bid_max=bid_max, render_mode=render_mode,
        )  # fmt: skip

        self.entities = entities
        self.tasks = tasks
        self.K = tasks.n_resources
        self.grid_size = grid_size
        self.travel = travel
        self.travel_cost = float(travel_cost)
        self.busy = busy
        self.consume = consume
        self.arrival = arrival
        self.arrival_period = int(arrival_period)
        self.arrival_count = (int(arrival_count[0]), int(arrival_count[1]))
        self.reward_scale = float(reward_scale)
        self.demand_noise = float(demand_noise)
        self.decay = float(decay)
        self.decay_after = int(decay_after)
        self.decay_while_committed = bool(decay_while_committed)
        self.one_step = one_step
        self.bidding = bidding
        self.bid_max = float(bid_max) if bid_max is not None else float(3.0 * max(entities.cost.max(), 1.0))
        self.strict = strict
        self.render_mode = render_mode
        self.has_positions = entities.positions is not None

        N, M, K = self.max_entities, self.max_tasks, self.K
        #: Columns of ``entity_features`` and ``task_features``.
        self.layout = ObsLayout(K)
        self.n_entity_features = self.layout.n_entity_features
        self.n_task_features = self.layout.n_task_features
        self.observation_space = self.layout.observation_space(N, M)
        self.action_space = spaces.MultiDiscrete(np.full(N, M + 1, dtype=np.int64))

        # Static padded entity arrays (never mutated; shared by deep copies).
        self._cost0 = entities.padded(entities.cost, N)
        self._supply0 = entities.padded(entities.supply, N)
        self._pos0 = entities.padded(entities.positions, N, width=2)  # integer cells stored as floats (no casts when moving)
        self._wire = entities.padded(entities.wire_cost, N)
        self._present0 = entities.padded(np.ones(n, dtype=bool), N)
        self._task_rows = tasks.rows * self.reward_scale
        self._eye = np.vstack([np.eye(M), np.zeros((1, M))])  # row M (= row -1) is "no task"
        self._entity_index = np.arange(N)
        self._tower_tables = static_tower_costs(self._pos0, self._wire, tasks.towers, travel)
        self._arrival: Arrival = make_arrival(arrival, len(tasks.rows), tasks.towers, self.arrival_count, grid_size)
        self._state_ready = False

    # ------------------------------------------------------------------ state

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict[str, np.ndarray], dict]:
        super().reset(seed=seed)
        self._init_state()
        self._last_choice = (
            np.full(self.max_entities, self.max_tasks, dtype=np.int64),
            np.zeros(self.max_entities, dtype=bool),
        )
        self._arrival.reset()
        self._arrive()
        return self._obs(), self._info(0, 0.0, 0.0, 0, np.zeros(self.max_entities))

    def set_bids(self, bids: np.ndarray) -> None:
        """Post the entities' bids (their wage) for the next allocation (``bidding=True`` only).

        :param bids: (n_entities,) or (max_entities,) non-negative bids, each at most ``bid_max``
        """
        if not self.bidding:
            raise RuntimeError("set_bids() needs an environment built with bidding=True")
        b = check_bids(bids, self.n_entities, self.max_entities, self.bid_max)
        self._bid[:] = 0.0
        self._bid[: b.shape[0]] = b
        self._geom_dirty = self._entities_dirty = True

    def observe(self) -> dict[str, np.ndarray]:
        """The current observation, e.g. after :meth:`set_bids` changed the pair costs between two steps."""
        if not self._state_ready:
            raise RuntimeError("call reset() before observe()")
        return self._obs()

    # ------------------------------------------------------------- queries

    def applied_action(self) -> np.ndarray:
        """(N,) the last action as the env applied it: mask-violating choices replaced by "unassigned" (M)."""
        a, valid = self._last_choice
        return np.where(valid, a, self.max_tasks)

    def action_masks(self) -> np.ndarray:
        """Flat (N·(M+1),) boolean mask in sb3-contrib's MultiDiscrete layout (used by MaskablePPO)."""
        if not self._state_ready:
            raise RuntimeError("call reset() before action_masks()")
        return self.layout.action_mask(self._free, self._open).astype(bool)

    def _obs(self) -> dict[str, np.ndarray]:
        # Padded entities and empty slots hold zeros in every state array, so no masking is needed here.
        self._refresh()
        lay = self.layout
        ef = self._ef_static.copy()  # cost, supply, position, bid: refreshed with the geometry
        if self._dist is not None and self.travel != "none":
            ef[:, lay.busy] = (self._dist[self._entity_index, self._assigned] + 1.0) * self._committed
        else:
            ef[:, lay.busy] = self._committed
        tf = lay.task_features(self._reward, self._rem, self._tpos, self._age)
        return lay.observation(ef, tf, self._pc_obs.copy(), self._free, self._open)

    def _info(
        self, completed: int, rewards: float, costs: float, invalid: int, income: np.ndarray, commitment: float = 0.0
    ) -> dict[str, Any]:
        return {
            "commitment_reward": commitment,
            "completed_tasks": completed,
            "task_reward_total": rewards,
            "cost_total": costs,
            "invalid_assignments": invalid,
            "entity_income": income,
        }

    # ----------------------------------------------------------------- step

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        if not self._state_ready:
            raise RuntimeError("call reset() before step()")
        a = check_action(action, self.max_entities, self.max_tasks)
        M = self.max_tasks
        chosen = a < M
        valid = chosen & self._free & self._open_ext[a]
        n_invalid = int(np.count_nonzero(chosen) - np.count_nonzero(valid))
        if n_invalid and self.strict:
            bad = np.flatnonzero(chosen & ~valid)
            raise ValueError(f"assignments of entities {bad.tolist()} violate the action mask (strict=True)")
        self._last_choice = (a, valid)  # the action as applied (for rendering), see :meth:`applied_action`

        # Commit: the pair cost is fixed when the entity is assigned.
        idx = valid.nonzero()[0]
        if idx.size:
            self._assigned[idx] = a[idx]
            self._charge[idx] = self._pc[idx, a[idx]]
        committed = self._assigned >= 0

        # Entities at their task's cell work; the others move one cell towards it.
        if self.travel != "none":
            _, arrived = travel_step(self._pos, self._tpos[self._assigned], committed, self.travel)
            self._geom_dirty = self._entities_dirty = True
            working = np.where(arrived, self._assigned, -1)
        else:
            working = self._assigned
        onehot = self._eye[working]
        contrib = onehot.T @ self._supply
        # Occupied tasks always have a positive demand, so covering it implies some arrived supply.
        covered = np.logical_and.reduce(contrib >= self._demand - EPS, axis=1)
        complete = self._occupied & covered & np.logical_or.reduce(contrib, axis=1)

        rewards, costs, n_complete, income, settled = self._complete(complete, committed)
        if not self.busy:  # never busy: assignments last one step
            self._assigned[:] = -1
            self._charge[:] = 0.0
        self._age_and_decay()

        self._t += 1
        if self._arrival.periodic and self._t % self.arrival_period == 0:
            self._arrive()

        exhausted = self._arrival.exhausted() and not self._occupied.any()
        terminated = self.one_step or not np.count_nonzero(self._alive) or exhausted
        obs = self._obs()
        commitment = rewards - costs - settled + self._settle_credits(bool(terminated))
        info = self._info(n_complete, rewards, costs, n_invalid, income, commitment)
        return obs, rewards - costs, bool(terminated), False, info

    # ------------------------------------------------------------ copying

    #: Attributes that never change after construction: deep copies share them.
    _SHARED: ClassVar[frozenset[str]] = frozenset(
        {"entities", "tasks", "observation_space", "action_space", "layout", "metadata", "spec"}
        | {"_cost0", "_supply0", "_pos0", "_wire", "_present0", "_eye", "_task_rows", "_entity_index"}
        | {"_tower_tables"}
    )

    def __deepcopy__(self, memo: dict[int, Any]) -> TaskAllocEnv:
        """Fast clone for planners: static tables and spaces are shared, the episode state is copied."""
        return clone(self, memo, self._SHARED)

    # ---------------------------------------------------------- rendering

    def render(self) -> np.ndarray | str | None:
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array' or 'ansi'")
            return None
        if self.render_mode == "ansi":
            return render_ansi(self.render_snapshot())
        return render_rgb(self.render_snapshot())

    def render_snapshot(self) -> RenderSnapshot:
        """What a picture of the current state needs (copies; see :mod:`envs.rendering`)."""
        if not self._state_ready:
            raise RuntimeError("call reset() before rendering")
        return RenderSnapshot(
            t=self._t,
            has_positions=self.has_positions,
            grid_size=self.grid_size,
            n_entities=self.n_entities,
            entity_pos=self._pos.copy(),
            task_pos=self._tpos.copy(),
            present=self._present0.copy(),
            alive=self._alive.copy(),
            free=self._free.copy(),
            assigned=self._assigned.copy(),
            shown=self._assigned.copy() if self.busy else np.where(self._last_choice[1], self._last_choice[0], -1),
            occupied=self._occupied.copy(),
            reward=self._reward.copy(),
            remaining=self._rem.copy(),
        )

    # ------------------------------------------------------------- accessors

    @property
    def base_costs(self) -> np.ndarray:
        """(N,) each entity's own base cost from its table (0 for padding): a bidding worker's reservation wage."""
        return self._cost0.copy()

    @property
    def bids(self) -> np.ndarray:
        """(N,) the bids posted with :meth:`set_bids` (0 before any)."""
        return self._bid.copy()
