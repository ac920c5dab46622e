"""Receding-horizon metaheuristic planners: genetic algorithm, particle swarm, symbiotic organisms search.

Every ``replan_every`` env steps the planner searches a plan for the next ``horizon`` steps on clones of the env: a
genome holds one task index per (step, entity) (``M`` = unassigned), and its fitness is the return of replaying it
on a clone (assignments the clone's mask refuses count as "unassigned"). Between re-plans the planner executes its
plan, repaired against the live mask. The population is seeded with the greedy allocator's rollout (and mutations
of it), so a search can only improve on greedy, and the best genome found so far is kept (elitism).

Fitness = the plan's return over the horizon plus the return of the greedy allocator continuing for ``tail`` more
steps on the same clone, so that teams committed near the end of the horizon are valued (a myopic horizon return
would prefer idling to slow tasks).

Futures: by default (``foresight=True``) the clones keep the env's random state, so the planner simulates the true
arrivals, as a planner with the simulator does: its plan is executable as planned, and it is the strongest form of
these baselines. ``foresight=False`` shares one sampled future among the rollouts of a re-plan (common random
numbers: the clones are re-seeded with one seed drawn by the planner); the plan is then repaired against the live
masks, and re-planning every step (``replan_every=1``) is advisable.

Defaults are the paper's settings (GA: population 100, mutation 0.05, crossover 0.5, 1000 generations; PSO: 100
particles, w 0.5, c1 = c2 = 1.5, 1000 iterations; SOS: 100 organisms, U(−1, 1) coefficients, 1000 iterations).
``budget`` caps the rollouts of one re-plan (iterations = budget // population): the paper's settings need 10⁵
rollouts per re-plan, minutes of CPU per step here. Fitness is a rollout per individual on a clone (the envs are
single-instance simulators); initialisation, operators and decoding are vectorised over the population.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from sb3_taskalloc.baselines.base import Allocator
from sb3_taskalloc.baselines.greedy import GreedyAllocator

Evaluate = Callable[[np.ndarray], np.ndarray]


class RecedingHorizonPlanner(Allocator):
    """Base class of the planners: re-planning on env clones, greedy seeding, repair, budget accounting.

    :param env: the env the planner acts in (the same object that is stepped, e.g. the one given to
        ``evaluate_policy``); it is cloned, never stepped
    :param population: individuals per iteration
    :param iterations: iterations per re-plan (paper: 1000)
    :param budget: at most this many search rollouts per re-plan, at least one round (the initial population and one
        iteration); None: ``population × (1 + iterations)``
    :param horizon: steps of a plan
    :param replan_every: env steps between re-plans
    :param tail: steps of greedy continuation added to each rollout's return
    :param foresight: plan on the env's own future (True) or on one sampled future per re-plan (False)
    :param seed: seed of the planner's generator
    """

    #: Rollouts per individual per iteration (sets the iterations a ``budget`` allows).
    rollouts_per_iteration = 1

    def __init__(
        self,
        env: gym.Env,
        population: int = 100,
        iterations: int = 1000,
        budget: int | None = None,
        horizon: int = 10,
        replan_every: int = 10,
        tail: int = 10,
        foresight: bool = True,
        seed: int | None = None,
    ) -> None:
        base = env.unwrapped
        if not hasattr(base, "observe") or not hasattr(base, "max_tasks"):
            raise ValueError(f"planners need a TaskAlloc env to clone, got {type(base).__name__}")
        if population < 2 or iterations < 1 or horizon < 1 or replan_every < 1:
            raise ValueError(f"need population >= 2 and iterations, horizon, replan_every >= 1, got {population}, "
                             f"{iterations}, {horizon}, {replan_every}")  # fmt: skip
        per_iteration = self.rollouts_per_iteration * population
        if budget is not None and budget < population + per_iteration:
            raise ValueError(
                f"budget ({budget} rollouts per re-plan) is below one search round of {type(self).__name__}: the initial "
                f"population ({population}) plus one iteration ({per_iteration}) = {population + per_iteration} rollouts"
            )
        self.env: Any = base
        self.population = population
        self.iterations = iterations if budget is None else (budget - population) // per_iteration
        self.budget = budget
        self.horizon = horizon
        self.replan_every = replan_every
        self.tail = tail
        self.foresight = foresight
        self.rng = np.random.default_rng(seed)
        self.greedy = GreedyAllocator()
        self._plan: np.ndarray | None = None
        self._k = 0
        self.last: dict[str, Any] = {}

    def reset(self, seed: int | None = None) -> None:
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self._plan = None

    def predict(
        self,
        observation: dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        if episode_start is not None and np.any(episode_start):
            self._plan = None
        masks = observation.get("entity_mask") if isinstance(observation, dict) else None
        if masks is not None and np.ndim(masks) == 2 and len(masks) > 1:
            raise ValueError("planners act in one env (they clone it): use a single env, not a VecEnv with several")
        return super().predict(observation, state, episode_start, deterministic)

    # ---------------------------------------------------------------- acting

    def allocate(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        if self._plan is None or self._k >= min(self.replan_every, self.horizon):
            live = self.env.observe()  # type: ignore[attr-defined]
            if not (
                np.array_equal(live["entity_mask"], obs["entity_mask"]) and np.array_equal(live["task_mask"], obs["task_mask"])
            ):
                raise ValueError("the observation does not match the planner's env: build the planner with the env it acts in")
            self._plan = self.plan()
            self._k = 0
        action = repair(self._plan[self._k], obs)
        self._k += 1
        return action

    def plan(self) -> np.ndarray:
        """Search a (horizon, N) plan from the env's current state; the result's fitness is in ``self.last``."""
        future = None if self.foresight else int(self.rng.integers(2**63))
        n_rollouts = 0

        def evaluate(genomes: np.ndarray) -> np.ndarray:
            nonlocal n_rollouts
            n_rollouts += len(genomes)
            return np.array([self.rollout(g, future) for g in genomes])

        seed_genome = self.greedy_genome(future)
        best, fitness = self.search(evaluate, seed_genome)
        self.last = {
            "fitness": float(fitness),
            "greedy_fitness": float(self.rollout(seed_genome, future)),
            "rollouts": n_rollouts,
        }
        return best

    # ------------------------------------------------------------- simulation

    def _clone(self, future: int | None) -> Any:
        clone = copy.deepcopy(self.env)
        clone.strict = False  # genomes may hold refused assignments: they count as "unassigned" in a rollout
        if future is not None:
            clone.np_random = np.random.default_rng(future)
        return clone

    def rollout(self, genome: np.ndarray, future: int | None) -> float:
        """Return of the plan over the horizon on a clone (refused assignments count as "unassigned"), plus ``tail``
        steps of greedy continuation."""
        clone = self._clone(future)
        total = 0.0
        obs: dict[str, np.ndarray] = {}
        for t in range(self.horizon + self.tail):
            obs, reward, terminated, _, _ = clone.step(genome[t] if t < self.horizon else self.greedy.allocate(obs))
            total += float(reward)
            if terminated:
                break
        return total

    def greedy_genome(self, future: int | None) -> np.ndarray:
        """The greedy allocator's actions over the horizon on a clone (the seed of every search)."""
        clone = self._clone(future)
        obs = clone.observe()
        genome = np.full((self.horizon, self.env.max_entities), self.env.max_tasks, dtype=np.int64)  # type: ignore[attr-defined]
        for t in range(self.horizon):
            genome[t] = self.greedy.allocate(obs)
            obs, _, terminated, _, _ = clone.step(genome[t])
            if terminated:
                break
        return genome

    def random_genomes(self, n: int, unassigned: float = 0.7) -> np.ndarray:
        """(n, horizon, N) genomes: each gene "unassigned" with probability ``unassigned``, else a uniform task slot."""
        M = self.env.max_tasks  # type: ignore[attr-defined]
        shape = (n, self.horizon, self.env.max_entities)  # type: ignore[attr-defined]
        tasks = self.rng.integers(0, M, size=shape)
        return np.where(self.rng.random(shape) < unassigned, M, tasks)

    def initial_genomes(self, seed_genome: np.ndarray, rate: float) -> np.ndarray:
        """(population, horizon, N): the seed (greedy rollout), mutations of it at ``rate``, and random genomes (half)."""
        P = self.population
        mutants = self.mutate(np.repeat(seed_genome[None], P // 2 - 1, 0), rate)
        return np.concatenate([seed_genome[None], mutants, self.random_genomes(P - P // 2)])

    def mutate(self, genomes: np.ndarray, rate: float) -> np.ndarray:
        """Re-draw each gene with probability ``rate`` (uniform over the M task slots and "unassigned")."""
        M = self.env.max_tasks  # type: ignore[attr-defined]
        redraw = self.rng.random(genomes.shape) < rate
        return np.where(redraw, self.rng.integers(0, M + 1, size=genomes.shape), genomes)

    def search(self, evaluate: Evaluate, seed_genome: np.ndarray) -> tuple[np.ndarray, float]:
        """Return the best genome found and its fitness."""
        raise NotImplementedError


def repair(action: np.ndarray, obs: dict[str, np.ndarray]) -> np.ndarray:
    """Replace the assignments the observation's mask refuses (busy entity, closed task) by "unassigned"."""
    M = len(obs["task_mask"])
    a = np.asarray(action, dtype=np.int64).copy()
    ok = (a < M) & obs["entity_mask"].astype(bool) & obs["task_mask"].astype(bool)[np.minimum(a, M - 1)]
    a[~ok] = M
    return a


class GeneticAlgorithm(RecedingHorizonPlanner):
    """Genetic algorithm: binary tournament selection, single-point crossover (rate 0.5) on the flattened genome,
    per-gene mutation (rate 0.05, uniform re-draw), elitism; seeded with the greedy rollout.

    :param env: see :class:`RecedingHorizonPlanner`
    :param mutation: per-gene mutation probability (paper 0.05)
    :param crossover: probability that a pair of parents is crossed (paper 0.5)
    :param population: paper 100
    :param iterations: generations (paper 1000)
    :param kwargs: :class:`RecedingHorizonPlanner` keywords (``budget``, ``horizon``, ``replan_every``, ``seed``, ...)
    """

    def __init__(
        self,
        env: gym.Env,
        mutation: float = 0.05,
        crossover: float = 0.5,
        population: int = 100,
        iterations: int = 1000,
        **kwargs: Any,
    ) -> None:
        super().__init__(env, population=population, iterations=iterations, **kwargs)
        self.mutation, self.crossover = mutation, crossover

    def search(self, evaluate: Evaluate, seed_genome: np.ndarray) -> tuple[np.ndarray, float]:
        P = self.population
        pop = self.initial_genomes(seed_genome, self.mutation)
        fit = evaluate(pop)
        for _ in range(self.iterations):
            a, b = self.rng.integers(0, P, size=(2, P))
            parents = pop[np.where(fit[a] >= fit[b], a, b)]  # binary tournaments
            flat = parents.reshape(P, -1)
            mates = flat[self.rng.permutation(P)]
            cut = self.rng.integers(1, flat.shape[1], size=(P, 1))
            cross = (self.rng.random((P, 1)) < self.crossover) & (np.arange(flat.shape[1]) >= cut)
            children = self.mutate(np.where(cross, mates, flat).reshape(pop.shape), self.mutation)
            child_fit = evaluate(children)
            elite = int(np.argmax(fit))
            worst = int(np.argmin(child_fit))
            children[worst], child_fit[worst] = pop[elite], fit[elite]  # elitism: the best survives
            pop, fit = children, child_fit
        best = int(np.argmax(fit))
        return pop[best], float(fit[best])


class _ContinuousPlanner(RecedingHorizonPlanner):
    """Planners over continuous positions x ∈ [0, M + 1) per gene, decoded as ⌊x⌋ (M = unassigned)."""

    def encode(self, genomes: np.ndarray) -> np.ndarray:
        return genomes + 0.5

    def decode(self, x: np.ndarray) -> np.ndarray:
        return np.clip(np.floor(x), 0, self.env.max_tasks).astype(np.int64)  # type: ignore[attr-defined]

    def clip(self, x: np.ndarray) -> np.ndarray:
        return np.clip(x, 0.0, self.env.max_tasks + 1 - 1e-6)  # type: ignore[attr-defined]

    def initial(self, seed_genome: np.ndarray) -> np.ndarray:
        P = self.population
        genomes = self.initial_genomes(seed_genome, 0.05)
        return self.encode(genomes) + self.rng.uniform(-0.4, 0.4, size=genomes.shape) * (np.arange(P) > 0)[:, None, None]


class ParticleSwarm(_ContinuousPlanner):
    """Particle swarm optimisation: v ← w·v + c1·r1·(p_best − x) + c2·r2·(g_best − x), x ← x + v.

    :param env: see :class:`RecedingHorizonPlanner`
    :param w: inertia (paper 0.5)
    :param c1: cognitive coefficient (paper 1.5)
    :param c2: social coefficient (paper 1.5)
    :param population: particles (paper 100)
    :param iterations: paper 1000
    :param kwargs: :class:`RecedingHorizonPlanner` keywords
    """

    def __init__(
        self,
        env: gym.Env,
        w: float = 0.5,
        c1: float = 1.5,
        c2: float = 1.5,
        population: int = 100,
        iterations: int = 1000,
        **kwargs: Any,
    ) -> None:
        super().__init__(env, population=population, iterations=iterations, **kwargs)
        self.w, self.c1, self.c2 = w, c1, c2

    def search(self, evaluate: Evaluate, seed_genome: np.ndarray) -> tuple[np.ndarray, float]:
        x = self.initial(seed_genome)
        v = np.zeros_like(x)
        fit = evaluate(self.decode(x))
        p_best, p_fit = x.copy(), fit.copy()
        g = int(np.argmax(p_fit))
        for _ in range(self.iterations):
            r1, r2 = self.rng.random(x.shape), self.rng.random(x.shape)
            v = self.w * v + self.c1 * r1 * (p_best - x) + self.c2 * r2 * (p_best[g] - x)
            x = self.clip(x + v)
            fit = evaluate(self.decode(x))
            better = fit > p_fit
            p_best[better], p_fit[better] = x[better], fit[better]
            g = int(np.argmax(p_fit))
        return self.decode(p_best[g]), float(p_fit[g])


class SymbioticOrganismsSearch(_ContinuousPlanner):
    """Symbiotic organisms search (Cheng & Prayogo): mutualism, commensalism (U(−1, 1) coefficients) and parasitism
    phases, each organism against a random partner, vectorised over the ecosystem; a move is kept only if it improves.

    :param env: see :class:`RecedingHorizonPlanner`
    :param population: organisms (paper 100)
    :param iterations: paper 1000 (each costs about 4 rollouts per organism)
    :param kwargs: :class:`RecedingHorizonPlanner` keywords
    """

    rollouts_per_iteration = 4  # mutualism (two), commensalism and parasitism

    def _keep_better(self, x: np.ndarray, fit: np.ndarray, idx: np.ndarray, cand: np.ndarray, evaluate: Evaluate) -> None:
        cand_fit = evaluate(self.decode(cand))
        better = cand_fit > fit[idx]
        x[idx[better]], fit[idx[better]] = cand[better], cand_fit[better]

    def search(self, evaluate: Evaluate, seed_genome: np.ndarray) -> tuple[np.ndarray, float]:
        P = self.population
        x = self.initial(seed_genome)
        fit = evaluate(self.decode(x))
        i = np.arange(P)
        for _ in range(self.iterations):
            best = x[int(np.argmax(fit))]
            j = (i + self.rng.integers(1, P, size=P)) % P  # a partner other than itself
            # Mutualism: both move towards the best, relative to their mutual vector.
            mutual = 0.5 * (x[i] + x[j])
            bf1, bf2 = self.rng.integers(1, 3, size=(2, P, 1, 1))
            cand_i = self.clip(x[i] + self.rng.random(x.shape) * (best - mutual * bf1))
            cand_j = self.clip(x[j] + self.rng.random(x.shape) * (best - mutual * bf2))
            self._keep_better(x, fit, i, cand_i, evaluate)
            self._keep_better(x, fit, j, cand_j, evaluate)
            # Commensalism: i benefits from j.
            best = x[int(np.argmax(fit))]
            self._keep_better(x, fit, i, self.clip(x[i] + self.rng.uniform(-1, 1, x.shape) * (best - x[j])), evaluate)
            # Parasitism: a mutated copy of i tries to replace j.
            M = self.env.max_tasks  # type: ignore[attr-defined]
            parasite = np.where(self.rng.random(x.shape) < 0.5, self.rng.uniform(0, M + 1, x.shape), x[i])
            self._keep_better(x, fit, j, self.clip(parasite), evaluate)
        best_idx = int(np.argmax(fit))
        return self.decode(x[best_idx]), float(fit[best_idx])
