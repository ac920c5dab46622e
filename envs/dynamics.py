"""The state mechanics of :class:`~envs.core.TaskAllocEnv`: its episode state, task arrivals, the quantities derived
from the state (distances, pair costs, remaining demand, masks), completions, decay and the commitment reward's
credits. ``TaskAllocEnv`` holds the API (spaces, reset, step, observation, rendering) on top of them.

These run at every step of every rollout on arrays of tens of rows, where NumPy's Python-level wrappers cost more than
the work: "is any set" is ``np.count_nonzero``, row reductions call the ufuncs' ``reduce``, and index lists come from
``.nonzero()`` (the envs' step rate, docs/benchmarks.md).
"""

from __future__ import annotations

import numpy as np

from envs.arrival import Arrival, ArrivalState
from envs.geometry import Travel, distances, pair_costs
from envs.layout import ObsLayout
from envs.tables import TaskTable
from envs.validation import EPS


class TaskAllocDynamics:
    """Mixin of :class:`~envs.core.TaskAllocEnv` with its state mechanics (the attributes are set there)."""

    max_entities: int
    max_tasks: int
    K: int
    has_positions: bool
    bidding: bool
    travel: Travel
    travel_cost: float
    consume: bool
    decay: float
    decay_after: int
    decay_while_committed: bool
    demand_noise: float
    tasks: TaskTable
    layout: ObsLayout
    np_random: np.random.Generator
    _arrival: Arrival
    _pos0: np.ndarray
    _present0: np.ndarray
    _cost0: np.ndarray
    _supply0: np.ndarray
    _wire: np.ndarray
    _eye: np.ndarray
    _task_rows: np.ndarray
    _state_ready: bool
    _pc: np.ndarray
    _dist: np.ndarray | None
    # Class-level defaults, so that an env pickled before these attributes existed (in a training checkpoint) steps on:
    # it takes the general pair-cost formula and rebuilds its entity features at its next observation.
    _tower_tables: tuple[np.ndarray, np.ndarray] | None = None
    _entities_dirty: bool = True

    # ------------------------------------------------------------------ state

    def _init_state(self) -> None:
        """A fresh episode state (every slot empty, every entity at its start)."""
        N, M, K = self.max_entities, self.max_tasks, self.K
        self._t = 0
        self._pos = self._pos0.copy()
        self._supply = self._supply0.copy()
        self._alive = self._present0.copy()  # present and not used up
        self._assigned = np.full(N, -1, dtype=np.int64)  # task slot an entity is committed to, -1 if free
        self._charge = np.zeros(N)  # pair cost fixed at commitment
        self._bid = np.zeros(N)
        self._occupied = np.zeros(M, dtype=bool)
        self._reward = np.zeros(M)
        self._base_demand = np.zeros((M, K))
        self._demand = np.zeros((M, K))  # current total demand (after decay and noise)
        self._tpos = np.zeros((M, 2))
        self._age = np.zeros(M, dtype=np.int64)
        self._tower = np.full(M, -1, dtype=np.int64)  # EPT: tower that is the task
        self._credit = np.zeros(M)  # profit credited to a closed task by ``info["commitment_reward"]``, not yet paid
        self._credited = np.zeros(M, dtype=bool)
        self._open_ext = np.zeros(M + 1, dtype=bool)
        self._dist: np.ndarray | None = None
        self._geom_dirty = True  # pair costs: positions, task slots or bids changed
        self._entities_dirty = True  # entity features: positions, supplies, presence or bids changed
        self._state_ready = True

    # ------------------------------------------------------------ arrivals

    def _free_slots(self) -> np.ndarray:
        return (~self._occupied).nonzero()[0]

    def _arrive(self) -> None:
        state = ArrivalState(self.np_random, len(self._free_slots()), self._tower[self._occupied], self._alive)
        rows, cells = self._arrival.draw(state)
        self._place(rows, cells)

    def _place(self, rows: np.ndarray, cells: np.ndarray | None = None) -> None:
        """Put table rows ``rows`` into the lowest free slots, at ``cells`` or (None) their table positions."""
        rows = np.asarray(rows, dtype=np.int64)
        if len(rows) == 0:
            return
        slots = self._free_slots()[: len(rows)]
        rows = rows[: len(slots)]
        self._geom_dirty = True
        table = self._task_rows[rows]
        self._occupied[slots] = True
        self._reward[slots] = table[:, 0]
        self._base_demand[slots] = table[:, 1:]
        self._demand[slots] = table[:, 1:]
        self._age[slots] = 0
        if self.tasks.towers is not None:
            towers = self.tasks.towers[rows]
            self._tower[slots] = towers
            self._tpos[slots] = self._pos0[towers]
        elif self.has_positions:
            if cells is not None:
                self._tpos[slots] = cells[: len(slots)]
            elif self.tasks.positions is not None:
                self._tpos[slots] = self.tasks.positions[rows]

    # ------------------------------------------------------------- queries

    def _refresh(self) -> None:
        """Recompute the derived quantities (distances, pair costs, remaining demand, masks) after a state change."""
        committed = self._assigned >= 0
        if np.count_nonzero(committed):
            onehot = self._eye[self._assigned]  # (N, M); row -1 of the padded identity is zero for free entities
            rem = np.maximum(self._demand - onehot.T @ self._supply, 0.0)  # empty slots have zero demand
        else:  # nothing committed (EPT after every step): the whole demand remains
            rem = self._demand.copy()
        free = self._alive & ~committed
        if self.tasks.towers is not None:
            free[self._tower[self._occupied]] = False  # a tower at peak demand cannot supply
        base = self._bid if self.bidding else self._cost0
        if self._geom_dirty:  # positions, task slots or bids changed since the last refresh
            if self._tower_tables is not None:  # EPT: towers never move, so each slot's column is its tower's
                dist, costs = self._tower_tables
                self._dist = dist[:, self._tower]  # column -1 (an empty slot) is the origin's
                self._pc = base[:, None] + costs[:, self._tower]
            elif self.has_positions:
                self._dist = distances(self._pos, self._tpos, self.travel)
                wire = self._wire if self.tasks.towers is not None else None
                self._pc = pair_costs(base, self._dist, self.travel_cost, wire, self._tower)
            else:
                self._dist = None
                self._pc = np.repeat(base[:, None], self.max_tasks, axis=1)
            # Observation pieces that only change with the geometry (padded rows and empty slots are zero).
            self._pc_obs = (self._pc * (self._present0[:, None] & self._occupied[None, :])).astype(np.float32)
            self._geom_dirty = False
        if self._entities_dirty:
            self._ef_static = self.layout.entity_features(base * self._alive, self._supply, self._pos, self._bid)
            self._entities_dirty = False
        self._rem = rem
        self._free = free
        self._open = self._occupied & np.logical_or.reduce(rem > EPS, axis=1)
        self._open_ext[: self.max_tasks] = self._open  # indexed by an action: "unassigned" (M) is never a task
        self._committed = committed

    # ------------------------------------------------------- completion

    def _complete(self, complete: np.ndarray, committed: np.ndarray) -> tuple[float, float, int, np.ndarray, float]:
        """Pay the tasks ``complete`` and release their teams (used up when ``consume``), free their slots and give
        EPT's task towers back. :return: the rewards, the charges, the number of tasks, each entity's income, and the
        credits of these tasks that the commitment reward already counted"""
        n_complete = int(np.count_nonzero(complete))
        if not n_complete:
            return 0.0, 0.0, 0, np.zeros(self.max_entities), 0.0
        team = committed & complete[self._assigned]
        income = self._charge * team
        rewards, costs = float(self._reward @ complete), float(income.sum())
        settled = float(self._credit @ complete)
        keep = ~complete
        self._credit *= keep
        self._credited &= keep
        if self.consume:
            self._alive &= ~team
            self._supply[team] = 0.0
            self._entities_dirty = True
        self._assigned[team] = -1
        self._charge[team] = 0.0
        self._occupied &= keep
        self._reward *= keep
        keep_rows = keep[:, None]
        self._demand *= keep_rows
        self._base_demand *= keep_rows
        self._tpos *= keep_rows
        self._geom_dirty = True
        self._age *= keep
        self._tower[complete] = -1
        return rewards, costs, n_complete, income, settled

    def _age_and_decay(self) -> None:
        """Age the occupied slots; decay (reward and demand × ρ once older than θ; positions untouched); redraw the
        changing demand."""
        M = self.max_tasks
        self._age += self._occupied
        if self.decay < 1.0:
            decaying = self._age > self.decay_after
            if not self.decay_while_committed:
                decaying &= np.bincount(self._assigned[self._assigned >= 0], minlength=M) == 0
            if np.count_nonzero(decaying):  # a factor of 1 everywhere changes nothing
                factor = np.where(decaying, self.decay, 1.0)
                self._reward *= factor
                self._base_demand *= factor[:, None]
        if self.demand_noise > 0:
            noise = self.np_random.uniform(1 - self.demand_noise, 1 + self.demand_noise, size=(M, 1))
            np.multiply(self._base_demand, noise, out=self._demand)
        else:
            self._demand[:] = self._base_demand

    def _settle_credits(self, terminated: bool) -> float:
        """The commitment reward's credits of this step (see the Rewards section): + (current reward − team charges) of
        each task that is closed (covered by committed entities) and not yet credited, − the credit of a task that
        reopened, and at termination − every credit still unpaid, so that an episode's commitment rewards sum to its
        return."""
        new = self._occupied & ~self._open & ~self._credited
        closing = np.count_nonzero(new)
        if not (closing or np.count_nonzero(self._credited)):  # nothing closes and nothing is owed (EPT's every step)
            return 0.0
        refund = self._credited & (self._open | ~self._occupied)
        profit_total = 0.0
        if closing:
            committed = self._assigned >= 0
            charges = np.bincount(self._assigned[committed], weights=self._charge[committed], minlength=self.max_tasks)
            profit = np.where(new, self._reward - charges, 0.0)
            self._credit += profit
            self._credited |= new
            profit_total = profit.sum()
        if terminated:
            refund |= self._credited
        total = float(profit_total - self._credit @ refund)
        self._credit *= ~refund
        self._credited &= ~refund
        return total
