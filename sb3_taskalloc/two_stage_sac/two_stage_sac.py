"""TwoStageSAC: discrete soft actor-critic for multi-entity task allocation."""

from __future__ import annotations

import io
import pathlib
import warnings
from collections import defaultdict
from typing import Any, ClassVar, Literal, TypeVar

import numpy as np
import torch as th
from stable_baselines3.common.base_class import maybe_make_env
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import obs_as_tensor

from sb3_taskalloc.common.buffers import TwoStageReplayBuffer, pack_decision
from sb3_taskalloc.common.policies import PreAssignActor, SelectCritic, Selector, TwinCritic
from sb3_taskalloc.common.save_util import AtomicSaveMixin, check_saved_model, saved_members
from sb3_taskalloc.two_stage_sac import dagger, graph_step, legacy
from sb3_taskalloc.two_stage_sac import updates as stage
from sb3_taskalloc.two_stage_sac.decoding import DecodingMixin
from sb3_taskalloc.two_stage_sac.graph_decide import DecisionGraph
from sb3_taskalloc.two_stage_sac.policies import TAMPolicy, check_spaces
from sb3_taskalloc.two_stage_sac.settings import check_select_kwargs, check_settings
from sb3_taskalloc.zoo_config import from_zoo

SelfTwoStageSAC = TypeVar("SelfTwoStageSAC", bound="TwoStageSAC")

#: Budget of ``learn()`` called without ``total_timesteps`` (env steps).
DEFAULT_TOTAL_TIMESTEPS = 20_000


class TwoStageSAC(AtomicSaveMixin, graph_step.GraphStepMixin, DecodingMixin, OffPolicyAlgorithm):
    """Two-stage discrete soft actor-critic (paper: "A Two-stage Reinforcement Learning-based Approach for
    Multi-entity Task Allocation"), for the ``TaskAlloc`` environments.

    One decision = two stages (paper Algorithm 1): each free entity takes a task from the TAM actor
    π_i(j|s) = softmax_j(h_i·g_j/√d) (candidate sets C_j); then every open task's pointer picks candidates until its
    demand is covered; a task whose profit (reward if covered − Σ pair costs) is ≤ 0 is abandoned.

    Every equation, and every deviation from the paper and from the published code, is an implementation detail of
    the package (``docs/implementation.md``); the comments cite them by number. :data:`PAPER_KWARGS` restores the
    paper's configuration. How a trained model decides at deployment is its decoding strategy (:meth:`set_decoder`).

    :param policy: ``"TAMPolicy"`` or a :class:`TAMPolicy` subclass
    :param env: a ``TaskAlloc`` environment (or its id)
    :param learning_rate: learning rate of every optimizer (constant or schedule)
    :param buffer_size: replay buffer size
    :param learning_starts: env steps of warm-up decisions (``warmup_exploration``) before learning
    :param batch_size: minibatch size
    :param tau: Polyak coefficient of the target networks
    :param gamma: discount factor of the stage-1 MDP
    :param train_freq: update the model every ``train_freq`` steps (int or (n, "step"|"episode"))
    :param gradient_steps: gradient steps per rollout (-1: as many as env steps collected)
    :param replay_buffer_class: replay buffer class (default :class:`TwoStageReplayBuffer`)
    :param replay_buffer_kwargs: extra replay buffer arguments
    :param n_steps: n-step returns for the stage-1 critics' target (implementation detail 2)
    :param ent_coef: stage-1 entropy coefficient α: ``"auto"``, ``"auto_0.1"`` (auto with initial value) or a float
    :param target_entropy_ratio: H̄* as a fraction of the maximum per-entity (or per-pick) entropy
    :param reward_timing: the stage-1 reward: ``"completion"`` (the env's, the paper's) or ``"commitment"`` (detail 2)
    :param entropy_bonus: the stage-1 entropy term: ``"sum"`` over the free entities (the paper's) or their ``"mean"``
    :param warmup_exploration: the warm-up's decisions: ``"uniform"`` (SB3's random warm-up) or ``"policy"`` (detail 8)
    :param train_preassign_actor: whether stage 1 learns: the pre-assign actor, its temperature and the AMIX critics
        that train it. ``False`` holds the actor at its initial rule while the select stage learns, and its critics,
        which nothing else reads, do not train (implementation detail 23)
    :param prior_coef: weight β of KL(π ‖ π₀) in the pre-assign actor's loss, π₀ its initial rule (detail 12)
    :param select_kwargs: the select stage's settings over :data:`~sb3_taskalloc.two_stage_sac.updates.SELECT_DEFAULTS`
    :param target_update_interval: target network update interval (gradient steps)
    :param cuda_graph: on CUDA, record the gradient step as a CUDA graph once and replay it (implementation detail 26,
        :mod:`.graph_step`), and the policy's own decisions per observation shape (detail 29, :mod:`.graph_decide`);
        eager elsewhere. Needs a constant learning rate
    :param stats_window_size: episodes in the rollout logging window
    :param tensorboard_log: tensorboard log folder
    :param policy_kwargs: :class:`TAMPolicy` keyword arguments (ablations included)
    :param verbose: 0, 1 or 2
    :param seed: random seed
    :param device: ``"auto"`` (CUDA when present), ``"cpu"``, ``"cuda"``
    :param _init_setup_model: build the networks at construction
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"TAMPolicy": TAMPolicy}
    policy: TAMPolicy
    replay_buffer: TwoStageReplayBuffer  # type: ignore[assignment]
    actor: PreAssignActor | None  # type: ignore[assignment]
    critic: TwinCritic | None
    critic_target: TwinCritic | None
    selector: Selector
    select_critic: SelectCritic
    select_critic_target: SelectCritic
    #: Set by :meth:`from_zoo`: the block's budget (``learn()``'s default) and its callbacks (run by each ``learn``).
    zoo_n_timesteps: int | None = None
    zoo_callbacks: tuple[Any, ...] | list[Any] = ()

    def __init__(
        self,
        policy: str | type[TAMPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 3e-4,
        buffer_size: int = 100_000,
        learning_starts: int = 500,
        batch_size: int = 64,
        tau: float = 0.02,
        gamma: float = 0.9,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        n_steps: int = 1,
        ent_coef: str | float = "auto",
        target_entropy_ratio: float = 0.05,
        reward_timing: Literal["completion", "commitment"] = "commitment",
        entropy_bonus: Literal["sum", "mean"] = "mean",
        warmup_exploration: Literal["uniform", "policy"] = "policy",
        train_preassign_actor: bool = True,
        prior_coef: float = 0.1,
        select_kwargs: dict[str, Any] | None = None,
        target_update_interval: int = 1,
        cuda_graph: bool = False,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        super().__init__(
            policy,
            env,
            learning_rate,
            buffer_size,
            learning_starts,
            batch_size,
            tau,
            gamma,
            train_freq,
            gradient_steps,
            action_noise=None,
            replay_buffer_class=replay_buffer_class or TwoStageReplayBuffer,
            replay_buffer_kwargs=replay_buffer_kwargs,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            seed=seed,
            use_sde=False,
            sde_support=False,
            supported_action_spaces=None,  # _setup_model's check_spaces names the observation and action layout
            support_multi_env=True,
        )
        legacy.check_policy_kwargs(self.policy_class, self.policy_kwargs)
        self.n_steps = n_steps
        if n_steps > 1:
            self.replay_buffer_kwargs = {**self.replay_buffer_kwargs, "n_steps": n_steps, "gamma": gamma}
        self.ent_coef = ent_coef
        self.target_entropy_ratio = target_entropy_ratio
        self.reward_timing = reward_timing
        self.entropy_bonus = entropy_bonus
        self.warmup_exploration = warmup_exploration
        self.train_preassign_actor = train_preassign_actor
        self.prior_coef = prior_coef
        self.select_kwargs = check_select_kwargs(select_kwargs)
        self.target_update_interval = target_update_interval
        self.cuda_graph = cuda_graph
        if _init_setup_model:
            self._setup_model()

    # ------------------------------------------------------------------ setup

    def _setup_model(self) -> None:
        check_settings(self)  # here, not in __init__, so that ``load(path, **kwargs)`` is checked too
        if self.observation_space is not None:
            check_spaces(self.observation_space, self.action_space)
        if self._vec_normalize_env is not None:
            raise ValueError(
                "VecNormalize is not supported by TwoStageSAC: TAMPolicy normalises its inputs itself (symlog) and needs the "
                "raw masks, demands and costs; remove the VecNormalize wrapper"
            )
        with warnings.catch_warnings():
            # SB3 warns that n_steps is ignored with a custom buffer class; TwoStageReplayBuffer gets it through
            # replay_buffer_kwargs (set in __init__), as the warning itself recommends.
            warnings.filterwarnings("ignore", message=r"`n_steps=\d+` is ignored because a custom", category=UserWarning)
            super()._setup_model()
        self._create_aliases()
        if self.select_kwargs["search_coef"] > 0 and not self.policy.preassign:
            raise ValueError(
                "select_kwargs['search_coef'] needs a pre-assigning policy: without pre-assignment (W/o Pre) the tasks pick "
                "from one shared pool, so their teams cannot be searched independently; set it to 0"
            )
        if not self.train_preassign_actor and self.actor is not None and not self.policy.preassign_rule:
            raise ValueError(
                "train_preassign_actor=False holds the pre-assign actor at its initial weights, and this policy's actor "
                "starts at random ones (heuristic_init=False, encoder='mlp' or pair_features=False): it would never learn "
                "to pre-assign; set train_preassign_actor=True"
            )
        lr = self.lr_schedule(1)
        self.log_ent_coef, self.ent_coef_optimizer, self.ent_coef_tensor = stage.entropy_coefficient(
            self.ent_coef, "ent_coef", self.device, lr
        )
        self.log_select_ent_coef, self.select_ent_coef_optimizer, self.select_ent_coef_tensor = stage.entropy_coefficient(
            self.select_kwargs["ent_coef"], "select_kwargs['ent_coef']", self.device, lr
        )
        # One update per trained stage: none for the pre-assignment of a policy without it ("W/o Pre"), or held at its
        # rule, where training its critics would change no decision (detail 23), unless a decoder reads them.
        self.updates: list[stage.PreAssignUpdate | stage.SelectUpdate] = [stage.SelectUpdate(self)]
        preassign = stage.preassign_update(self)
        if preassign is not None:
            self.updates.insert(0, preassign)
        graph_step.check_cuda_graph(self)
        self.gradient_step = graph_step.gradient_step(self)
        self.policy.decision_graph = DecisionGraph() if self.cuda_graph else None

    def _create_aliases(self) -> None:
        self.actor = self.policy.actor
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target
        self.selector = self.policy.selector
        self.select_critic = self.policy.select_critic
        self.select_critic_target = self.policy.select_critic_target

    def _get_policy_from_name(self, policy_name: str) -> type[BasePolicy]:
        if policy_name not in self.policy_aliases:  # SB3's own message names neither the cause nor the choice
            raise ValueError(
                f"TwoStageSAC has no policy {policy_name!r}: it takes {', '.join(self.policy_aliases)} (or a subclass), "
                "whose attention reads the TaskAlloc Dict observation at any number of entities and tasks"
            )
        return super()._get_policy_from_name(policy_name)

    def _learned_rewards(self, reward: np.ndarray, infos: list[dict[str, Any]]) -> np.ndarray:
        """The reward the stage-1 critics learn: the env's, or its commitment reward with ``reward_timing="commitment"``
        (implementation detail 2)."""
        if self.reward_timing != "commitment":
            return reward
        try:
            return np.array([info["commitment_reward"] for info in infos], dtype=np.float32)
        except KeyError:
            raise ValueError(
                "reward_timing='commitment' needs info['commitment_reward'] from the env (the TaskAlloc envs provide "
                "it); use reward_timing='completion' with other envs"
            ) from None

    # ------------------------------------------------------------------ acting

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """Masked exploration: during warm-up uniformly random valid pre-assignments and picks (``warmup_exploration=
        "uniform"``), otherwise the stochastic policy. Returns the env action and the packed decision stored in the
        replay buffer."""
        assert self._last_obs is not None, "self._last_obs was not set"
        uniform = self.num_timesteps < learning_starts and self.warmup_exploration == "uniform"
        self.policy.set_training_mode(False)
        with th.inference_mode():
            view = self.policy.parse(obs_as_tensor(self._last_obs, self.device))  # type: ignore[arg-type]
            decision = self.policy.decide(view, deterministic=False, uniform=uniform)
        action = decision.env_action.cpu().numpy()
        buffer_action = pack_decision(action, decision.candidates.cpu().numpy(), decision.pick_rank.cpu().numpy())
        return action, buffer_action

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: np.ndarray | dict[str, np.ndarray],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """SB3's storage, with the commitment reward in place of the env reward when ``reward_timing="commitment"``
        (the episode statistics keep the env reward)."""
        super()._store_transition(replay_buffer, buffer_action, new_obs, self._learned_rewards(reward, infos), dones, infos)

    # ------------------------------------------------------------------ training

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        self.policy.set_training_mode(True)
        self._update_learning_rate(stage.optimizers(self))
        logs: stage.Logs = defaultdict(list)

        for gradient_step in range(gradient_steps):
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[arg-type]
            # Stage 1, pre-assignment (Algorithm 2), then stage 2, select (Algorithm 3): each update runs target →
            # critic → actor → temperature (sb3_taskalloc.two_stage_sac.updates), eagerly or replayed from the step's
            # CUDA graph (graph_step).
            self.gradient_step(replay_data, logs)  # type: ignore[arg-type]
            # Target networks: Polyak averaging every ``target_update_interval`` gradient steps.
            if gradient_step % self.target_update_interval == 0:
                for update in self.updates:
                    update.update_target()

        read = stage.read_logs(self, logs, gradient_steps)
        self._n_updates += gradient_steps
        stage.check_parameters(self)
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, values in read.items():
            self.logger.record(f"train/{key}", float(np.mean(values)))

    # ------------------------------------------------------------------ API

    @classmethod
    def from_zoo(cls: type[SelfTwoStageSAC], env_id: str, seed: int | None = None, **overrides: Any) -> SelfTwoStageSAC:
        """The recommended configuration of ``env_id``: its block of the shipped zoo config (``n_envs`` copies of the
        env, the tuned keywords, the block's budget as ``learn()``'s default, its DAgger run when ``learn`` ends);
        ``overrides`` go over it (:func:`sb3_taskalloc.zoo_config.from_zoo`)."""
        return from_zoo(cls, env_id, seed, **overrides)

    def learn(
        self: SelfTwoStageSAC,
        total_timesteps: int | None = None,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "TwoStageSAC",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfTwoStageSAC:
        """Train for ``total_timesteps`` env steps (default: the zoo block's budget for a model made by :meth:`from_zoo`,
        else :data:`DEFAULT_TOTAL_TIMESTEPS` = 20,000); a :meth:`from_zoo` model also runs its block's callbacks."""
        if total_timesteps is None:
            total_timesteps = self.zoo_n_timesteps or DEFAULT_TOTAL_TIMESTEPS
        callback, progress_bar = dagger.learn_callbacks(self.zoo_callbacks, callback, progress_bar)
        if not (isinstance(total_timesteps, int | np.integer) and total_timesteps >= 0):
            raise ValueError(f"total_timesteps must be a non-negative integer, got {total_timesteps!r}")
        end = total_timesteps + (0 if reset_num_timesteps else self.num_timesteps)
        if end <= self.learning_starts:
            warnings.warn(
                f"learn({total_timesteps}) ends at env step {end}, within the warm-up (learning_starts="
                f"{self.learning_starts}): no gradient step will run, and the model stays as it is",
                stacklevel=2,
            )
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )

    def check_distillable(self) -> None:
        """A clear error where :meth:`distill_select` cannot teach this model's pointer (a policy without pre-assignment),
        for a schedule that runs it after training (:class:`.SelectDAggerCallback`) to call before training."""
        if not self.policy.preassign:
            raise ValueError("distill_select needs a pre-assigning policy: without pre-assignment the tasks share one pool")

    def distill_select(self, env: GymEnv | str, **kwargs: Any) -> list[dict[str, float]]:
        """Teach the pointer the exact most profitable cover of its candidates by DAgger (implementation detail 19):
        :func:`.dagger.distill_select` on this model, whose keywords (``iterations``, ``episodes``, ``epochs``,
        ``learning_rate``, ``batch_size``, ``imitation``, ``seed``, ``progress_bar``, ``callback``) it takes; returns
        each iteration's figures."""
        return dagger.distill_select(self, env, **kwargs)

    def set_env(self, env: GymEnv | str, force_reset: bool = True) -> None:
        """Attach an env (or an env id). With a size-agnostic policy the env may have other entity/task counts (zero-shot
        transfer): the spaces are adopted and the replay buffer is rebuilt for the new sizes. Feature sizes must match."""
        env = self._wrap_env(maybe_make_env(env, self.verbose), self.verbose)  # type: ignore[arg-type]
        new_obs, new_act = env.observation_space, env.action_space
        check_spaces(new_obs, new_act)
        if new_obs != self.observation_space:
            self.policy.check_transfer(new_obs)  # type: ignore[arg-type]
            self.observation_space, self.action_space = new_obs, new_act
            self.policy.observation_space, self.policy.action_space = new_obs, new_act
        if self.replay_buffer is not None and (
            self.replay_buffer.observation_space != new_obs or self.replay_buffer.n_envs != env.num_envs
        ):
            # The stored transitions have the old sizes (or env count): start a fresh buffer for fine-tuning.
            self.replay_buffer = TwoStageReplayBuffer(
                self.buffer_size,
                new_obs,  # type: ignore[arg-type]
                new_act,
                device=self.device,
                n_envs=env.num_envs,
                **(self.replay_buffer_kwargs or {}),
            )
        super().set_env(env, force_reset)

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfTwoStageSAC],
        path: Any,
        env: GymEnv | str | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> SelfTwoStageSAC:
        """Load a model; ``env`` (or an env id) may have other entity/task counts when the policy is size-agnostic (see
        :meth:`set_env`) and another number of envs (a model trained on ``n_envs`` copies loads on one env to evaluate or
        transfer). A model saved by an earlier version loads with its settings converted (:mod:`.legacy`)."""
        decoder = None
        if isinstance(path, str | pathlib.Path):
            check_saved_model(path, ("data", "policy.pth"))
            custom_objects, kwargs, decoder = legacy.load_arguments(path, custom_objects, kwargs)
        try:
            model = super().load(
                path, env=None, device=device, custom_objects=custom_objects, print_system_info=print_system_info, **kwargs
            )
        except KeyError as error:  # SB3's fallback for old DQN saves hides its "parameters do not match" (the context)
            states = [name.removesuffix(".pth") for name in saved_members(path) if name.endswith(".pth")]
            raise ValueError(
                f"{path} lacks saved state (it holds {states}; {error.__context__ or error}): it was edited or written "
                "by another program. Its weights load into a new model with model.set_parameters(path, exact_match=False)"
            ) from error
        legacy.finish(model, decoder)
        if env is not None:
            env = model._wrap_env(maybe_make_env(env, model.verbose), model.verbose)  # type: ignore[arg-type]
            model.n_envs = env.num_envs  # another env count is fine on load, as in SB3's ``load`` (not in ``set_env``)
            model.set_env(env, force_reset)
        return model

    def load_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase, truncate_last_traj: bool = True) -> None:
        """SB3's load, refusing a buffer whose spaces differ from this model's (another entity or task count): its
        transitions could not be trained on."""
        current = self.replay_buffer
        super().load_replay_buffer(path, truncate_last_traj)
        loaded = self.replay_buffer
        if not isinstance(loaded, TwoStageReplayBuffer) or loaded.observation_space != self.observation_space:
            self.replay_buffer = current
            got = loaded.observation_space if isinstance(loaded, TwoStageReplayBuffer) else type(loaded).__name__
            raise ValueError(
                f"the replay buffer in {path} was filled on another env: its observation space {got} differs from this "
                f"model's {self.observation_space}"
            )

    def _excluded_save_params(self) -> list[str]:
        aliases = ["actor", "critic", "critic_target", "selector", "select_critic", "select_critic_target"]
        return [*super()._excluded_save_params(), *aliases, "updates", "gradient_step", "zoo_callbacks"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = ["policy", "selector.optimizer", "select_critic.optimizer"]
        if self.actor is not None:
            state_dicts += ["actor.optimizer", "critic.optimizer"]
        variables = []
        for log_name, opt_name, fixed in (
            ("log_ent_coef", "ent_coef_optimizer", "ent_coef_tensor"),
            ("log_select_ent_coef", "select_ent_coef_optimizer", "select_ent_coef_tensor"),
        ):
            if getattr(self, opt_name, None) is not None:
                variables.append(log_name)
                state_dicts.append(opt_name)
            else:
                variables.append(fixed)
        return state_dicts, variables
