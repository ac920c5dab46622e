"""Replay buffer of TwoStageSAC: observations plus the two-stage decision.

Besides SB3's Dict replay data it stores, per transition, the candidate sets of the pre-assignment
(``candidates[j, i]``: entity i was a candidate of task j when j was decoded) and the pick order of the select stage
(``pick_steps[j, i]``: 1 + the step at which task j picked entity i, 0 if not picked; zero means "not picked" so that
the array is allocated lazily, like SB3's own ``np.zeros`` arrays, and a model built for evaluation never touches its
memory). The environment action is derived from them and stored as SB3 does.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import DictReplayBuffer
from stable_baselines3.common.vec_env import VecNormalize

from sb3_taskalloc.common.utils import check_counts


class TwoStageReplayBufferSamples(NamedTuple):
    observations: dict[str, th.Tensor]
    actions: th.Tensor  # (B, N) env action
    next_observations: dict[str, th.Tensor]
    dones: th.Tensor  # (B, 1)
    rewards: th.Tensor  # (B, 1)
    candidates: th.Tensor  # (B, M, N) bool
    pick_rank: th.Tensor  # (B, M, N) long, −1 = not picked
    discounts: th.Tensor | None = None  # (B, 1) γ^k of the bootstrap after k ≤ n steps (n-step returns), else None


def pack_decision(env_action: np.ndarray, candidates: np.ndarray, pick_rank: np.ndarray) -> np.ndarray:
    """Pack (n_envs, N) env actions, (n_envs, M, N) candidates and pick ranks into one (n_envs, N + 2·M·N) array,
    the ``buffer_action`` that SB3's ``collect_rollouts`` hands to :meth:`TwoStageReplayBuffer.add`."""
    n = env_action.shape[0]
    return np.concatenate(
        [env_action.reshape(n, -1), candidates.reshape(n, -1).astype(np.int64), pick_rank.reshape(n, -1)], axis=1
    ).astype(np.int64)


def unpack_decision(packed: np.ndarray, n_entities: int, n_tasks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`pack_decision`."""
    n = packed.shape[0]
    N, M = n_entities, n_tasks
    if packed.shape[1] != N + 2 * M * N:
        raise ValueError(f"packed decision must have {N + 2 * M * N} columns for N={N}, M={M}, got {packed.shape[1]}")
    action = packed[:, :N]
    cand = packed[:, N : N + M * N].reshape(n, M, N).astype(bool)
    rank = packed[:, N + M * N :].reshape(n, M, N)
    return action, cand, rank


class TwoStageReplayBuffer(DictReplayBuffer):
    """Dict replay buffer that also keeps the two-stage decision of each transition.

    :param buffer_size: max number of transitions
    :param observation_space: the env's Dict observation space
    :param action_space: the env's MultiDiscrete action space
    :param device: torch device of the sampled tensors
    :param n_envs: number of parallel envs
    :param optimize_memory_usage: not supported (Dict observations)
    :param handle_timeout_termination: treat time-limit truncation as non-terminal (SB3 semantics)
    :param n_steps: sample n-step returns Σ_{k<n} γ^k r_{t+k} with the observation after the last of those steps as
        next observation, cut at the end of the episode (SB3's ``NStepReplayBuffer`` arithmetic); 1: one-step
        transitions
    :param gamma: discount of the n-step returns
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Dict,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        n_steps: int = 1,
        gamma: float = 0.99,
    ) -> None:
        check_counts({"n_steps": n_steps})
        self.n_steps = n_steps
        self.gamma = float(gamma)
        super().__init__(
            buffer_size, observation_space, action_space, device, n_envs, optimize_memory_usage, handle_timeout_termination
        )
        self.n_entities = int(observation_space["entity_mask"].shape[0])  # type: ignore[index]
        self.n_tasks = int(observation_space["task_mask"].shape[0])  # type: ignore[index]
        N, M = self.n_entities, self.n_tasks
        index_dtype = np.int16 if N < 2**15 else np.int32
        self.actions = np.zeros((self.buffer_size, self.n_envs, N), dtype=index_dtype)
        self.candidates = np.zeros((self.buffer_size, self.n_envs, M, N), dtype=bool)
        self.pick_steps = np.zeros((self.buffer_size, self.n_envs, M, N), dtype=index_dtype)

    def __getstate__(self) -> dict[str, Any]:
        """The buffer's state with only its stored rows: the arrays are allocated for ``buffer_size`` transitions (2.3 GB
        on RBF at the default size), and pickling them whole wrote that much for a buffer of a few hundred."""
        state = self.__dict__.copy()
        if self.full:
            return state
        sliced = []  # (attribute, key in a dict attribute or None)
        for name, value in self.__dict__.items():
            if isinstance(value, dict):
                state[name] = dict(value)
                for key, array in value.items():
                    if self._row_array(array):
                        state[name][key] = array[: self.pos]
                        sliced.append((name, key))
            elif self._row_array(value):
                state[name] = value[: self.pos]
                sliced.append((name, None))
        state["_stored_rows"] = (self.pos, sliced)
        return state

    def _row_array(self, value: Any) -> bool:
        """Whether ``value`` is one of the arrays with a row per transition."""
        return isinstance(value, np.ndarray) and value.ndim >= 1 and len(value) == self.buffer_size

    def __setstate__(self, state: dict[str, Any]) -> None:
        if "pick_rank" in state:  # a buffer pickled with ``pick_rank`` (steps from 0, −1: not picked) loads too
            state["pick_steps"] = state.pop("pick_rank") + 1
        if "_stored_rows" in state:  # pickled with its stored rows only: the rest is allocated again, empty
            rows, sliced = state.pop("_stored_rows")
            for name, key in sliced:
                stored = state[name] if key is None else state[name][key]
                array = np.zeros((state["buffer_size"], *stored.shape[1:]), dtype=stored.dtype)
                array[:rows] = stored
                if key is None:
                    state[name] = array
                else:
                    state[name][key] = array
        self.__dict__.update(state)

    def add(  # type: ignore[override]
        self,
        obs: dict[str, np.ndarray],
        next_obs: dict[str, np.ndarray],
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        env_action, cand, rank = unpack_decision(np.asarray(action).reshape(self.n_envs, -1), self.n_entities, self.n_tasks)
        self.candidates[self.pos] = cand
        self.pick_steps[self.pos] = rank + 1
        super().add(obs, next_obs, env_action, reward, done, infos)

    def _get_samples(  # type: ignore[override]
        self,
        batch_inds: np.ndarray,
        env: VecNormalize | None = None,
        env_indices: np.ndarray | None = None,
    ) -> TwoStageReplayBufferSamples:
        """The transitions at rows ``batch_inds`` of envs ``env_indices`` (random envs by default, as SB3's)."""
        if env_indices is None:
            env_indices = np.random.randint(0, high=self.n_envs, size=(len(batch_inds),))
        obs = {key: self.to_torch(v[batch_inds, env_indices]) for key, v in self.observations.items()}
        if self.n_steps == 1:
            last, discounts = batch_inds, None
            rewards = self.rewards[batch_inds, env_indices]
        else:
            last, rewards, gamma_k = self._n_step(batch_inds, env_indices)
            discounts = self.to_torch(gamma_k).reshape(-1, 1)
        next_obs = {key: self.to_torch(v[last, env_indices]) for key, v in self.next_observations.items()}
        dones = self.dones[last, env_indices] * (1 - self.timeouts[last, env_indices])
        return TwoStageReplayBufferSamples(
            observations=obs,
            actions=th.as_tensor(self.actions[batch_inds, env_indices].astype(np.int64), device=self.device),
            next_observations=next_obs,
            dones=self.to_torch(dones).reshape(-1, 1),
            rewards=self.to_torch(rewards).reshape(-1, 1),
            candidates=th.as_tensor(self.candidates[batch_inds, env_indices], device=self.device),
            pick_rank=th.as_tensor(self.pick_steps[batch_inds, env_indices].astype(np.int64) - 1, device=self.device),
            discounts=discounts,
        )

    def _n_step(self, batch_inds: np.ndarray, env_indices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(index of the last step, n-step return, γ^k) of each sampled transition: the return sums the rewards of up to
        ``n_steps`` steps, stopping after the first step that ends its episode (terminal or truncated) and before the
        write position, whose successor is not stored yet."""
        steps = np.arange(self.n_steps)
        indices = (batch_inds[:, None] + steps) % self.buffer_size  # (B, n)
        env = env_indices[:, None]
        ends = np.logical_or(self.dones[indices, env], self.timeouts[indices, env])
        ends[:, :-1] |= indices[:, :-1] == (self.pos - 1) % self.buffer_size  # the newest stored step ends the window
        last_k = np.where(ends.any(1), ends.argmax(1), self.n_steps - 1)
        mask = steps[None, :] <= last_k[:, None]
        returns = (self.rewards[indices, env] * (self.gamma**steps)[None, :] * mask).sum(1)
        last = (batch_inds + last_k) % self.buffer_size
        return last, returns.astype(np.float32), (self.gamma ** (last_k + 1)).astype(np.float32)

    def nbytes_per_transition(self) -> int:
        """Bytes stored per transition (observations, next observations, decision, reward, flags)."""
        total = sum(v.nbytes for v in self.observations.values()) + sum(v.nbytes for v in self.next_observations.values())
        total += self.actions.nbytes + self.candidates.nbytes + self.pick_steps.nbytes
        total += self.rewards.nbytes + self.dones.nbytes + self.timeouts.nbytes
        return total // (self.buffer_size * self.n_envs)
