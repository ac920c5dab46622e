"""TwoStageSAC: discrete soft actor-critic for multi-entity task allocation."""

from __future__ import annotations

import copy
import io
import math
import pathlib
import warnings
from collections import defaultdict
from collections.abc import Callable
from typing import Any, ClassVar, Literal, NamedTuple, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import maybe_make_env
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule
from stable_baselines3.common.utils import obs_as_tensor
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecEnvWrapper

import sb3_taskalloc.two_stage_sac.losses as losses
from sb3_taskalloc.common.buffers import (
    CounterfactualBuffer,
    TwoStageReplayBuffer,
    TwoStageReplayBufferSamples,
    concat_samples,
    pack_decision,
)
from sb3_taskalloc.common.distributions import MaskedCategorical
from sb3_taskalloc.common.policies import PreAssignActor, SelectCritic, Selector, TwinCritic
from sb3_taskalloc.common.save_util import AtomicSaveMixin, check_saved_model
from sb3_taskalloc.common.torch_layers import ObsView
from sb3_taskalloc.common.utils import check_choices, check_counts, foreach_polyak_update
from sb3_taskalloc.two_stage_sac.policies import TAMPolicy, check_spaces

SelfTwoStageSAC = TypeVar("SelfTwoStageSAC", bound="TwoStageSAC")


class _CoverLabel(NamedTuple):
    """One decoding round labelled for :meth:`TwoStageSAC.distill_select` (a batch row of one)."""

    view: ObsView
    task_of: th.Tensor  # (1, N) the round's candidate sets
    rank: th.Tensor  # (1, M, N) each task's labelled team in pick order
    labelled: th.Tensor  # (1, M) tasks whose team is a label


#: Budget of ``learn()`` called without ``total_timesteps`` (env steps).
DEFAULT_TOTAL_TIMESTEPS = 20_000

#: Keywords of the paper's configuration, ``TwoStageSAC("TAMPolicy", env, **PAPER_KWARGS)``: γ 0.98 and τ 0.005, the
#: joint entropy bonus with the entropy target of the earlier defaults, the env reward as paid on completion, a uniform
#: warm-up, no prior term, PyTorch's initialisation (κ = κ_s = 1) and the paper's critic. The defaults differ where the
#: learning experiment measured that the paper's setting does not learn within its budget (implementation details 2, 8,
#: 10 and 12).
PAPER_KWARGS: dict[str, Any] = {
    "gamma": 0.98,
    "tau": 0.005,
    "target_entropy_ratio": 0.3,
    "entropy_bonus": "sum",
    "reward_timing": "completion",
    "warmup_exploration": "uniform",
    "prior_coef": 0.0,
    "select_prior_coef": 0.0,
    "train_preassign_actor": True,
    "policy_kwargs": {"heuristic_init": False, "team_value": False},
}


def check_distill_select(
    iterations: int, episodes: int, epochs: int, learning_rate: float, batch_size: int, imitation: str
) -> None:
    """A clear error for the first bad argument of :meth:`TwoStageSAC.distill_select` (named as there), so that a
    schedule that runs it after training (:class:`.SelectDAggerCallback`) can refuse it before training."""
    check_counts({"iterations": iterations, "episodes": episodes, "epochs": epochs, "batch_size": batch_size})
    check_choices({"imitation": (imitation, ("sequence", "set"))})
    if not learning_rate > 0:
        raise ValueError(f"learning_rate must be positive, got {learning_rate!r}")


class TwoStageSAC(AtomicSaveMixin, OffPolicyAlgorithm):
    """Two-stage discrete soft actor-critic (paper: "A Two-stage Reinforcement Learning-based Approach for
    Multi-entity Task Allocation"), for the ``TaskAlloc`` environments.

    One decision = two stages (paper Algorithm 1): each free entity samples a task from the TAM actor
    π_i(j|s) = softmax_j(h_i·g_j/√d) (pre-assignment, candidate sets C_j); then, for every open task in parallel,
    a pointer head picks candidates one by one until the task's demand is covered; a task whose internal profit
    (reward if covered − Σ pair costs) is ≤ 0 is abandoned.

    Every equation, and every deviation from the paper and from the published code, is an implementation detail of
    the package (:mod:`sb3_taskalloc.two_stage_sac`); the comments below cite them by number.

    The defaults are the configuration under which the policy learns on RBF, MT, EPT and Almighty in the learning
    experiment (``python -m sb3_taskalloc.experiments learn``): rule-initialised actors held near their rules by a KL
    prior, the profit credited at commitment, the per-entity mean entropy with a low target, γ 0.9 and τ 0.02.
    :data:`PAPER_KWARGS` restores the paper's configuration. Training on ``n_envs`` copies of the env (one batched
    decision for all of them, ``gradient_steps`` per batch) is what the zoo configs use.

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
    :param n_steps: n-step returns for the stage-1 critics' target (implementation detail 2): the target sums up to
        ``n_steps`` discounted env rewards before bootstrapping, so rewards that arrive steps after the decision that
        earned them reach its value in one update (SB3's ``n_steps`` of SAC)
    :param ent_coef: stage-1 entropy coefficient α: ``"auto"``, ``"auto_0.1"`` (auto with initial value) or a float
    :param select_ent_coef: select-stage entropy coefficient α_s (same forms)
    :param target_entropy_ratio: H̄* as a fraction of the maximum per-entity (or per-pick) entropy
    :param warmup_exploration: how the warm-up decides: ``"uniform"`` random valid pre-assignments and picks (SB3's
        random warm-up), or ``"policy"``, the stochastic policy itself (with ``heuristic_init``, samples of the
        cost-greedy rules), so that the first transitions the critics learn from resemble the deployed behaviour
        (implementation detail 8)
    :param reward_timing: the reward the stage-1 critics learn from: ``"completion"``, the env reward (paid when a team
        has arrived and covers its task, the paper's), or ``"commitment"``, the env's ``info["commitment_reward"]``:
        the same profit credited in the step its team is committed (implementation detail 2), which sums to the same
        return over an episode but lets the decision that earned a profit see it
    :param entropy_bonus: the stage-1 entropy term of the target and the actor loss: ``"sum"`` over the free entities
        (the joint entropy, the paper's) or their ``"mean"`` (implementation detail 2)
    :param actor_warmup: gradient steps during which only the critics learn: the pre-assign actor, the pointer and
        both temperatures keep their initial values (with ``heuristic_init``, the critics first learn the values of the
        cost-greedy rules before the actors follow them)
    :param train_preassign_actor: whether the pre-assign actor and its temperature learn; ``False`` keeps them at their
        initial values for the whole training (implementation detail 23) while the critics and the select stage learn.
        ``False`` needs an actor that starts at the rule (:func:`~sb3_taskalloc.two_stage_sac.policies.starts_at_rule`)
        or a policy without one ("W/o Pre"): a random actor held at its start would never pre-assign by anything
    :param prior_coef: weight β of KL(π ‖ π₀) in the pre-assign actor's loss, π₀ = the actor at initialisation (a
        frozen copy in the policy): learning departs from the initial rule only where the critics' values outweigh it
    :param select_prior_coef: the same weight β_s for the pointer (select stage)
    :param profit_coef: weight λ of the exact one-step improvement term in the pre-assign actor's loss (implementation
        detail 14, not in the paper; 0: off): moving single entities to other tasks and decoding the teams again gives
        the change of the step's profit without the critics
    :param profit_entities: entities moved per state by that term
    :param profit_batch_size: rows of each minibatch used by that term (each costs ``profit_entities`` × M decodes)
    :param search_coef: weight λ_s of the search-distillation term in the pre-assign actor's loss (implementation detail
        16, not in the paper; 0: off): the actor learns the best of ``search_samples`` sampled pre-assignments of a
        state by the step's profit, where it beats the argmax
    :param search_samples: pre-assignments per state of that term, the argmax included
    :param search_temperature: temperature of that term's samples
    :param search_batch_size: rows of each minibatch used by that term (each costs ``search_samples`` decodes)
    :param select_search_coef: weight λ_p of the select-stage search-distillation term in the pointer's loss
        (implementation detail 18, not in the paper; 0: off): each task's pointer learns the best of
        ``select_search_samples`` decodes of its team by the task's profit, where it beats the deterministic decode
        (pre-assigning policies only)
    :param select_search_samples: decodes per task of that term, the deterministic one included
    :param select_search_temperature: temperature of that term's sampled decodes
    :param select_search_method: how that term finds a better team: ``"sample"``, the best of the sampled decodes, or
        ``"exact"``, the exact most profitable cover of the task's candidates (HiGHS, one solve per minibatch row on
        the CPU; ``select_search_samples`` and ``select_search_temperature`` are then unused)
    :param select_search_batch_size: rows of the select stage's minibatch used by that term (None: all
        ``select_batch_size``; fewer bound the cost of the exact method's solves)
    :param counterfactual_rate: share of the collection steps at which every env also steps a copy of itself with a
        second decision sampled at the same state (implementation detail 17, not in the paper; 0: off; the envs must
        live in this process, as in a ``DummyVecEnv``): the copy shares the env's random state, so both transitions
        differ only by the decision, and the stage-1 critics learn from both
    :param counterfactual_batch_size: branched transitions added to each stage-1 minibatch
    :param counterfactual_coef: weight of a paired term of the stage-1 critic loss: each branched transition comes with
        the replayed one of its state, and the difference of the critic's values is fitted to the difference of their
        targets; 0: the branched transitions alone join the minibatch, in the ordinary loss
    :param target_update_interval: target network update interval (gradient steps)
    :param select_batch_size: rows of each minibatch used by the select stage (each row holds up to M × team-size
        transitions, so a few rows suffice; the decoding loop is the costly part of a gradient step)
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
        select_ent_coef: str | float = "auto",
        target_entropy_ratio: float = 0.05,
        reward_timing: Literal["completion", "commitment"] = "commitment",
        entropy_bonus: Literal["sum", "mean"] = "mean",
        warmup_exploration: Literal["uniform", "policy"] = "policy",
        actor_warmup: int = 0,
        train_preassign_actor: bool = True,
        prior_coef: float = 0.1,
        select_prior_coef: float = 3.0,
        profit_coef: float = 0.0,
        profit_entities: int = 4,
        profit_batch_size: int = 4,
        search_coef: float = 0.0,
        search_samples: int = 32,
        search_temperature: float = 2.0,
        search_batch_size: int = 16,
        select_search_coef: float = 0.0,
        select_search_samples: int = 16,
        select_search_temperature: float = 1.0,
        select_search_method: str = "sample",
        select_search_batch_size: int | None = None,
        counterfactual_rate: float = 0.0,
        counterfactual_batch_size: int = 32,
        counterfactual_coef: float = 0.0,
        target_update_interval: int = 1,
        select_batch_size: int = 16,
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
            supported_action_spaces=(spaces.MultiDiscrete,),
            support_multi_env=True,
        )
        counts = {
            "batch_size": batch_size,
            "target_update_interval": target_update_interval,
            "select_batch_size": select_batch_size,
            "n_steps": n_steps,
            "profit_entities": profit_entities,
            "profit_batch_size": profit_batch_size,
            "search_samples": search_samples,
            "search_batch_size": search_batch_size,
            "select_search_samples": select_search_samples,
            "counterfactual_batch_size": counterfactual_batch_size,
            **({} if select_search_batch_size is None else {"select_search_batch_size": select_search_batch_size}),
        }
        check_counts(counts)
        check_choices(
            {
                "reward_timing": (reward_timing, ("completion", "commitment")),
                "entropy_bonus": (entropy_bonus, ("sum", "mean")),
                "warmup_exploration": (warmup_exploration, ("uniform", "policy")),
                "select_search_method": (select_search_method, ("sample", "exact")),
            }
        )
        self.n_steps = n_steps
        if n_steps > 1:
            self.replay_buffer_kwargs = {**self.replay_buffer_kwargs, "n_steps": n_steps, "gamma": gamma}
        self.ent_coef = ent_coef
        self.select_ent_coef = select_ent_coef
        self.target_entropy_ratio = target_entropy_ratio
        self.reward_timing = reward_timing
        self.entropy_bonus = entropy_bonus
        self.warmup_exploration = warmup_exploration
        if actor_warmup < 0:
            raise ValueError(f"actor_warmup must be >= 0 gradient steps, got {actor_warmup}")
        self.actor_warmup = actor_warmup
        self.train_preassign_actor = train_preassign_actor
        if not train_preassign_actor and (profit_coef > 0 or search_coef > 0):
            raise ValueError(
                f"profit_coef ({profit_coef}) and search_coef ({search_coef}) are terms of the pre-assign actor's loss: "
                "they need train_preassign_actor=True"
            )
        weights = {
            "prior_coef": prior_coef,
            "select_prior_coef": select_prior_coef,
            "profit_coef": profit_coef,
            "search_coef": search_coef,
            "select_search_coef": select_search_coef,
        }
        for name, weight in weights.items():
            if not (math.isfinite(weight) and weight >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0, got {weight!r}")
        temperatures = {"search_temperature": search_temperature, "select_search_temperature": select_search_temperature}
        for name, temperature in temperatures.items():
            if not (math.isfinite(temperature) and temperature > 0.0):
                raise ValueError(f"{name} must be a finite number > 0, got {temperature!r}")
        self.profit_coef = float(profit_coef)
        self.profit_entities = profit_entities
        self.profit_batch_size = profit_batch_size
        self.search_coef = float(search_coef)
        self.search_samples = search_samples
        self.search_temperature = float(search_temperature)
        self.search_batch_size = search_batch_size
        self.select_search_coef = float(select_search_coef)
        self.select_search_samples = select_search_samples
        self.select_search_temperature = float(select_search_temperature)
        self.select_search_method = select_search_method
        self.select_search_batch_size = select_search_batch_size
        if not (isinstance(counterfactual_rate, int | float) and 0.0 <= counterfactual_rate <= 1.0):
            raise ValueError(f"counterfactual_rate must be a share in [0, 1], got {counterfactual_rate!r}")
        self.counterfactual_rate = float(counterfactual_rate)
        self.counterfactual_batch_size = counterfactual_batch_size
        if not (
            isinstance(counterfactual_coef, int | float) and math.isfinite(counterfactual_coef) and counterfactual_coef >= 0
        ):
            raise ValueError(f"counterfactual_coef must be a finite number >= 0, got {counterfactual_coef!r}")
        self.counterfactual_coef = float(counterfactual_coef)
        self.counterfactual_buffer: CounterfactualBuffer | None = None
        self._branched = False
        self.prior_coef = float(prior_coef)
        self.select_prior_coef = float(select_prior_coef)
        self.target_update_interval = target_update_interval
        self.select_batch_size = select_batch_size
        if _init_setup_model:
            self._setup_model()

    # ------------------------------------------------------------------ setup

    def _setup_model(self) -> None:
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
        if self.select_search_coef > 0 and not self.policy.preassign:
            raise ValueError(
                "select_search_coef needs a pre-assigning policy: without pre-assignment (W/o Pre) the tasks pick from one "
                "shared pool, so their teams cannot be searched independently; set select_search_coef=0"
            )
        if not self.train_preassign_actor and self.actor is not None and not self.policy.preassign_rule:
            raise ValueError(
                "train_preassign_actor=False holds the pre-assign actor at its initial weights, and this policy's actor "
                "starts at random ones (heuristic_init=False, encoder='mlp' or pair_features=False): it would never learn "
                "to pre-assign; set train_preassign_actor=True"
            )
        self.counterfactual_buffer = self._make_counterfactual_buffer()
        self.log_ent_coef, self.ent_coef_optimizer, self.ent_coef_tensor = self._entropy_coefficient(self.ent_coef, "ent_coef")
        self.log_select_ent_coef, self.select_ent_coef_optimizer, self.select_ent_coef_tensor = self._entropy_coefficient(
            self.select_ent_coef, "select_ent_coef"
        )

    def _entropy_coefficient(
        self, spec: str | float, name: str
    ) -> tuple[th.Tensor | None, th.optim.Optimizer | None, th.Tensor | None]:
        """(log α parameter, its optimizer, None) for ``"auto[_init]"``, or (None, None, α) for a float ≥ 0."""
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
            log_alpha = th.log(th.ones(1, device=self.device) * init).requires_grad_(True)
            return log_alpha, th.optim.Adam([log_alpha], lr=self.lr_schedule(1)), None
        if not (isinstance(spec, int | float) and math.isfinite(spec) and spec >= 0):
            raise ValueError(f"{name} must be 'auto', 'auto_<initial value>' or a float >= 0, got {spec!r}")
        return None, None, th.tensor(float(spec), device=self.device)

    def _create_aliases(self) -> None:
        self.actor = self.policy.actor
        self.critic = self.policy.critic
        self.critic_target = self.policy.critic_target
        self.selector = self.policy.selector
        self.select_critic = self.policy.select_critic
        self.select_critic_target = self.policy.select_critic_target

    def _make_counterfactual_buffer(self) -> CounterfactualBuffer | None:
        """The buffer of the branched transitions (implementation detail 17), one-step, row for row beside the replay
        buffer; None when ``counterfactual_rate`` is 0."""
        if self.counterfactual_rate == 0.0 or self.observation_space is None:
            return None
        if self.env is not None:
            self._branchable_envs()  # refuse envs it cannot copy now, not at the first branched step
        return CounterfactualBuffer(
            self.buffer_size,
            self.observation_space,  # type: ignore[arg-type]
            self.action_space,
            device=self.device,
            n_envs=self.n_envs,
        )

    def _branchable_envs(self) -> list[Any]:
        """The envs of the training VecEnv as objects of this process, below any ``Monitor`` (which writes its episodes
        to a file and is bookkeeping only), so that a deep copy steps like the env itself."""
        venv: Any = self.env
        while isinstance(venv, VecEnvWrapper):
            venv = venv.venv
        if not isinstance(venv, DummyVecEnv):
            raise ValueError(
                f"counterfactual_rate > 0 copies the training envs, which needs them in this process (DummyVecEnv, the "
                f"default of make_vec_env); got {type(venv).__name__}"
            )
        envs = []
        for env in venv.envs:
            while isinstance(env, Monitor):
                env = env.env
            envs.append(env)
        return envs

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

    def _branch(self, view: ObsView, uniform: bool) -> None:
        """Implementation detail 17: a second decision c′ sampled at the current states, taken by deep copies of the
        envs (which share their random state, so c and c′ meet the same arrivals and noise), stored as one-step
        transitions in :attr:`counterfactual_buffer`. The critics then see two decisions of one state: Q(s, c) − Q(s, c′)
        is what the actor's gradient follows, and a single sampled decision per state rarely shows it."""
        assert self.counterfactual_buffer is not None and self._last_obs is not None
        other = self.policy.decide(view, deterministic=False, uniform=uniform)
        action = other.env_action.cpu().numpy()
        steps = [copy.deepcopy(env).step(a) for env, a in zip(self._branchable_envs(), action, strict=True)]
        next_obs = {key: np.stack([s[0][key] for s in steps]) for key in steps[0][0]}
        terminated = np.array([s[2] for s in steps])
        truncated = np.array([s[3] for s in steps])
        ends = zip(terminated, truncated, strict=True)
        infos = [{**s[4], "TimeLimit.truncated": bool(tr and not te)} for s, (te, tr) in zip(steps, ends, strict=True)]
        reward = self._learned_rewards(np.array([s[1] for s in steps], dtype=np.float32), infos)
        packed = pack_decision(action, other.candidates.cpu().numpy(), other.pick_rank.cpu().numpy())
        row = self.replay_buffer.pos  # where the replayed transition of these states goes next
        self.counterfactual_buffer.add_at(row, self._last_obs, next_obs, packed, reward, terminated | truncated, infos)  # type: ignore[arg-type]
        self._branched = True

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
            if self.counterfactual_buffer is not None and np.random.random() < self.counterfactual_rate:
                self._branch(view, uniform)
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
        reward = self._learned_rewards(reward, infos)
        if self.counterfactual_buffer is not None and isinstance(replay_buffer, TwoStageReplayBuffer):
            if not self._branched:
                self.counterfactual_buffer.clear(replay_buffer.pos)
            self._branched = False
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)

    # ------------------------------------------------------------------ training

    def _sample(self, batch_size: int) -> tuple[TwoStageReplayBufferSamples, int]:
        """A minibatch of ``batch_size`` replayed transitions, followed, when there are branched transitions
        (implementation detail 17), by K = ``counterfactual_batch_size`` of them; with the paired term
        (``counterfactual_coef`` > 0) the K replayed transitions of their states come first, row for row. The select
        stage and the terms computed on the first rows keep the replayed ones.

        :return: the minibatch and the number of pairs (0 without the paired term)
        """
        replay_data: TwoStageReplayBufferSamples = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[assignment]
        if self.counterfactual_buffer is None or self.counterfactual_buffer.size() == 0:
            return replay_data, 0
        paired = self.counterfactual_coef > 0
        branched, replayed = self.counterfactual_buffer.sample_branched(
            self.counterfactual_batch_size, self.replay_buffer if paired else None
        )
        if replayed is None:
            return concat_samples(replay_data, branched, self.gamma), 0
        pairs = concat_samples(replayed, branched, self.gamma)
        return concat_samples(replay_data, pairs, self.gamma), self.counterfactual_batch_size

    def _with_paired_term(
        self, critic: losses.PreAssignCriticLoss, start: int, n_pairs: int, logs: dict[str, list[float]]
    ) -> th.Tensor:
        """The stage-1 critic loss plus the paired term on the counterfactual pairs from row ``start`` (detail 17)."""
        if n_pairs == 0:
            return critic.loss
        paired = losses.paired_critic_loss(critic.current, critic.target_q, start, n_pairs)
        logs["paired_critic_loss"].append(paired.item())
        return critic.loss + self.counterfactual_coef * paired

    @staticmethod
    def _first_rows(view: ObsView, dist: MaskedCategorical, n: int) -> tuple[ObsView, MaskedCategorical]:
        """The first ``n`` rows of a minibatch and of the actor's distribution on it (the actor pass is reused)."""
        rows_view = ObsView(*(x[:n] for x in view))
        return rows_view, MaskedCategorical(dist.logits[:n], rows_view.valid)

    @staticmethod
    def _alpha(log_alpha: th.Tensor | None, fixed: th.Tensor | None) -> th.Tensor:
        """The temperature as a constant of this gradient step: exp(log α) when tuned, else the fixed value."""
        return th.exp(log_alpha.detach()) if log_alpha is not None else fixed  # type: ignore[return-value]

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        self.policy.set_training_mode(True)
        optimizers: list[th.optim.Optimizer] = [self.selector.optimizer, self.select_critic.optimizer]
        if self.actor is not None and self.critic is not None:
            optimizers += [self.actor.optimizer, self.critic.optimizer]
        self._update_learning_rate(optimizers)
        logs: dict[str, list[float]] = defaultdict(list)

        for gradient_step in range(gradient_steps):
            replay_data, n_pairs = self._sample(batch_size)
            obs = self.policy.parse(replay_data.observations)
            # During the critic warm-up (implementation detail 11) only the critics learn: the actors and the
            # temperatures keep their initial values.
            actors_learn = self._n_updates + gradient_step >= self.actor_warmup
            preassign_learns = actors_learn and self.train_preassign_actor

            # Stage 1, pre-assignment (paper: Pre-assign Module, Algorithm 2).
            if self.actor is not None and self.critic is not None and self.critic_target is not None:
                alpha = self._alpha(self.log_ent_coef, self.ent_coef_tensor)
                logs["ent_coef"].append(alpha.item())
                # Critic: the soft TD target of L_critic(φ) on the stored pre-assignment (details 2–3).
                critic = losses.preassign_critic_loss(
                    self.actor,
                    self.critic,
                    self.critic_target,
                    obs,
                    self.policy.parse(replay_data.next_observations),
                    replay_data.rewards.squeeze(-1),
                    replay_data.dones.squeeze(-1),
                    replay_data.candidates,
                    self.gamma if replay_data.discounts is None else replay_data.discounts.squeeze(-1),
                    alpha,
                    self.entropy_bonus == "mean",
                )
                logs["critic_loss"].append(critic.loss.item())
                critic_loss = self._with_paired_term(critic, batch_size, n_pairs, logs)
                if not preassign_learns:
                    self._step(self.critic.optimizer, critic_loss)
                else:
                    dist = self.actor(obs)
                    # Temperature: log α·(H̄ − H̄*) on the mean per-entity entropy (detail 4).
                    if self.log_ent_coef is not None and self.ent_coef_optimizer is not None:
                        entropy = losses.preassign_entropy(dist, obs, self.target_entropy_ratio)
                        if entropy.entropy.numel() > 0:
                            ent_loss = losses.ent_coef_loss(self.log_ent_coef, entropy.entropy, entropy.target)
                            logs["ent_coef_loss"].append(self._step(self.ent_coef_optimizer, ent_loss))
                    # Actor: L_actor(θ) on the same critic values as the critic loss (detail 3), + β KL(π ‖ π₀) (detail 12).
                    actor_loss = losses.preassign_actor_loss(
                        dist,
                        self.critic,
                        critic.contexts,
                        obs,
                        alpha,
                        self.policy.actor_prior,
                        self.prior_coef,
                        self.entropy_bonus == "mean",
                    )
                    logs["actor_loss"].append(actor_loss.item())
                    # Exact one-step improvement on the first rows (detail 14): each costs profit_entities × M decodes.
                    if self.profit_coef > 0:
                        rows_view, rows_dist = self._first_rows(obs, dist, self.profit_batch_size)
                        profit = losses.preassign_profit_loss(rows_dist, self.selector.head, rows_view, self.profit_entities)
                        logs["profit_loss"].append(profit.item())
                        actor_loss = actor_loss + self.profit_coef * profit
                    # Search distillation on the first rows (detail 16): each costs search_samples decodes.
                    if self.search_coef > 0:
                        rows_view, rows_dist = self._first_rows(obs, dist, self.search_batch_size)
                        search = losses.preassign_search_loss(
                            rows_dist, self.selector.head, rows_view, self.search_samples, self.search_temperature
                        )
                        logs["search_loss"].append(search.loss.item())
                        logs["search_improved"].append(search.improved.item())
                        logs["search_gain"].append(search.gain.item())
                        actor_loss = actor_loss + self.search_coef * search.loss
                    # Disjoint parameters: one backward pass gives each network its own gradient.
                    self.critic.optimizer.zero_grad()
                    self.actor.optimizer.zero_grad()
                    (critic_loss + actor_loss).backward()
                    self.critic.optimizer.step()
                    self.actor.optimizer.step()

            # Stage 2, select (paper: Select Module, Algorithm 3).
            self._train_select(obs, replay_data, actors_learn, logs)

            # Target networks: Polyak averaging every ``target_update_interval`` gradient steps.
            if gradient_step % self.target_update_interval == 0:
                if self.critic is not None and self.critic_target is not None:
                    foreach_polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                foreach_polyak_update(self.select_critic.parameters(), self.select_critic_target.parameters(), self.tau)

        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, values in logs.items():
            self.logger.record(f"train/{key}", float(np.mean(values)))

    def _train_select(
        self, obs: ObsView, replay_data: TwoStageReplayBufferSamples, actors_learn: bool, logs: dict[str, list[float]]
    ) -> None:
        """One select-stage update: discrete SAC on the stored pick orders (detail 5), on the first ``select_batch_size``
        rows (each holds up to M × team-size transitions), and the search-distillation term (detail 18).

        :param obs: the minibatch's parsed observations
        :param actors_learn: the pointer and its temperature learn (false during the critic warm-up)
        :param logs: the update's log values, appended to
        """
        select_alpha = self._alpha(self.log_select_ent_coef, self.select_ent_coef_tensor)
        logs["select_ent_coef"].append(select_alpha.item())
        rows = slice(0, self.select_batch_size)
        view = ObsView(*(x[rows] for x in obs))
        select = losses.select_losses(
            self.selector,
            self.select_critic,
            self.select_critic_target,
            view,
            replay_data.candidates[rows],
            replay_data.pick_rank[rows],
            self.policy.preassign,
            select_alpha,
            self.target_entropy_ratio,
            self.policy.selector_prior,
            self.select_prior_coef if actors_learn else 0.0,  # the prior term enters only the actor loss
        )
        if select is None:
            return
        if actors_learn and self.log_select_ent_coef is not None and self.select_ent_coef_optimizer is not None:
            ent_loss = losses.ent_coef_loss(self.log_select_ent_coef, select.entropy, select.target_entropy)
            logs["select_ent_coef_loss"].append(self._step(self.select_ent_coef_optimizer, ent_loss))
        logs["select_critic_loss"].append(self._step(self.select_critic.optimizer, select.critic_loss))
        if not actors_learn:
            return
        actor_loss = select.actor_loss
        if self.select_search_coef > 0:  # each row costs select_search_samples decodes, or a HiGHS solve
            n = self.select_search_batch_size or self.select_batch_size
            found = losses.select_search_loss(
                self.selector,
                ObsView(*(x[:n] for x in view)),
                replay_data.candidates[rows][:n],
                self.select_search_samples,
                self.select_search_temperature,
                self.select_search_method,
            )
            logs["select_search_loss"].append(found.loss.item())
            logs["select_search_improved"].append(found.improved.item())
            logs["select_search_gain"].append(found.gain.item())
            actor_loss = actor_loss + self.select_search_coef * found.loss
        logs["select_actor_loss"].append(self._step(self.selector.optimizer, actor_loss))

    @staticmethod
    def _step(optimizer: th.optim.Optimizer, loss: th.Tensor) -> float:
        """One optimizer step on ``loss``; returns its value."""
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        return loss.item()

    # ------------------------------------------------------------------ API

    def learn(
        self: SelfTwoStageSAC,
        total_timesteps: int = DEFAULT_TOTAL_TIMESTEPS,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "TwoStageSAC",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfTwoStageSAC:
        """Train for ``total_timesteps`` env steps (default :data:`DEFAULT_TOTAL_TIMESTEPS` = 20,000)."""
        if not (isinstance(total_timesteps, int | np.integer) and total_timesteps >= 0):
            raise ValueError(f"total_timesteps must be a non-negative integer, got {total_timesteps!r}")
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

    def distill_select(
        self,
        env: GymEnv | str,
        iterations: int = 4,
        episodes: int = 10,
        epochs: int = 8,
        learning_rate: float = 1e-3,
        batch_size: int = 32,
        imitation: str = "sequence",
        seed: int | None = None,
        progress_bar: bool = False,
        callback: Callable[[dict[str, float]], bool | None] | None = None,
    ) -> list[dict[str, float]]:
        """Teach the pointer the exact most profitable cover of its candidates by DAgger (implementation detail 19).

        Each iteration runs the deterministic policy for ``episodes`` episodes on ``env``, labels every decoding round
        it met (every pre-assign round of every step) with each task's better team of its deterministic decode and the
        exact cover of its candidates (:func:`.select_stage.cover_search`), and fits the pointer alone, by
        ``epochs`` passes of Adam over every label gathered so far, to the labelled teams (teacher-forced
        log-likelihood). The pre-assign actor, the critics and the replay buffer are untouched; ``learn`` may go on
        afterwards.

        :param env: the env (or env id) of the rollouts; a VecEnv runs its copies in one batched decision
        :param iterations: rollout-label-fit iterations
        :param episodes: episodes rolled out per iteration (counted over all copies of a VecEnv)
        :param epochs: passes over the labels per iteration
        :param learning_rate: Adam's step size
        :param batch_size: decoding rounds per gradient step
        :param imitation: ``"sequence"``: the likelihood of each labelled pick in the label's order; ``"set"``: of
            picking any member of the cover not picked yet (:func:`.losses.cover_imitation_loss`)
        :param seed: seed of the rollouts' env (None: as it comes); use seeds disjoint from the evaluation episodes
        :param progress_bar: show the rollout episodes with tqdm
        :param callback: called with each iteration's figures after its fit (an evaluation, a checkpoint); ``False``
            stops DAgger there, as a callback's ``False`` stops ``learn``
        :return: per iteration: the rollouts' mean return and env steps, the rounds met and the tasks labelled, the
            share of the tasks with candidates whose exact cover beats the deterministic team and the mean profit gain
            over those tasks, the last epoch's mean loss
        """
        from tqdm.auto import tqdm

        self.check_distillable()
        check_distill_select(iterations, episodes, epochs, learning_rate, batch_size, imitation)
        vec_env = self._wrap_env(maybe_make_env(env, self.verbose), self.verbose)
        check_spaces(vec_env.observation_space, vec_env.action_space)
        if vec_env.observation_space != self.observation_space:
            self.policy.check_transfer(vec_env.observation_space)  # type: ignore[arg-type]
        if seed is not None:
            vec_env.seed(seed)
        optimizer = th.optim.Adam(self.policy.selector.head.parameters(), lr=learning_rate)
        rng = np.random.default_rng(seed)
        labels: list[_CoverLabel] = []
        history: list[dict[str, float]] = []
        obs = vec_env.reset()
        with tqdm(total=iterations * episodes, desc="select-stage DAgger", disable=not progress_bar) as bar:
            for it in range(iterations):
                obs, stats = self._label_rollouts(vec_env, obs, episodes, labels, bar.update)
                stats["loss"] = self._fit_labels(labels, optimizer, epochs, batch_size, rng, imitation == "set")
                history.append({"iteration": float(it + 1), **stats})
                if self.verbose >= 1:
                    print(f"select-stage DAgger {history[-1]}")
                if callback is not None and callback(history[-1]) is False:
                    break
        return history

    def _label_rollouts(
        self, vec_env: VecEnv, obs: Any, episodes: int, labels: list[_CoverLabel], done_episode: Any
    ) -> tuple[Any, dict[str, float]]:
        """DAgger's data (:meth:`distill_select`): ``episodes`` episodes of the deterministic policy, every decoding
        round labelled with each task's better team of its decode and the exact cover (:func:`.cover_search`); each
        batch row with a labelled task joins ``labels``. :return: the last observation, and the rollouts' figures"""
        from sb3_taskalloc.two_stage_sac.select_stage import cover_search

        self.policy.set_training_mode(False)
        head = self.policy.selector.head
        returns: list[float] = []
        running = np.zeros(vec_env.num_envs)
        totals = dict.fromkeys(("steps", "rounds", "tasks", "labelled_tasks", "improved", "gain"), 0.0)
        while len(returns) < episodes:
            rounds: list[tuple[ObsView, th.Tensor]] = []
            with th.inference_mode():
                view = self.policy.parse(self.policy.obs_to_tensor(obs)[0])
                action = self.policy.decide(view, deterministic=True, rounds_out=rounds).env_action
                for round_view, task_of in rounds:
                    found = cover_search(head, round_view, task_of)
                    slots = th.arange(found.profit.shape[1], device=task_of.device).view(1, -1, 1)
                    has = (task_of.unsqueeze(1) == slots).any(-1)  # (B, M) tasks with candidates
                    labelled = has & (found.profit > 0)  # a kept team: an abandoned decode teaches nothing
                    totals["rounds"] += int(has.any(-1).sum())
                    totals["tasks"] += int(has.sum())
                    totals["labelled_tasks"] += int(labelled.sum())
                    totals["improved"] += int((has & (found.profit > found.base)).sum())
                    totals["gain"] += float((found.profit - found.base)[has].sum())
                    for b in th.nonzero(labelled.any(-1)).flatten().tolist():
                        rows = slice(b, b + 1)
                        view_row = ObsView(*(x[rows].clone() for x in round_view))
                        labels.append(_CoverLabel(view_row, task_of[rows].clone(), found.rank[rows].clone(), labelled[rows]))
            obs, reward, done, _ = vec_env.step(action.cpu().numpy())
            totals["steps"] += vec_env.num_envs
            running += reward
            for k in np.flatnonzero(done):
                if len(returns) < episodes:
                    returns.append(float(running[k]))
                    done_episode(1)
                running[k] = 0.0
        tasks = max(totals.pop("tasks"), 1.0)
        shares = {"improved": totals.pop("improved") / tasks, "gain": totals.pop("gain") / tasks}
        return obs, {"mean_return": float(np.mean(returns)), **totals, **shares}

    def _fit_labels(
        self,
        labels: list[_CoverLabel],
        optimizer: th.optim.Optimizer,
        epochs: int,
        batch_size: int,
        rng: np.random.Generator,
        as_set: bool = False,
    ) -> float:
        """``epochs`` passes of ``optimizer`` over ``labels`` in random minibatches of the pointer's teacher-forced
        log-likelihood (:func:`.losses.cover_imitation_loss`). :return: the last pass's mean loss"""
        head = self.policy.selector.head
        self.policy.set_training_mode(True)
        epoch_losses: list[float] = []
        for _ in range(epochs):
            order = rng.permutation(len(labels))
            epoch_losses = []
            for start in range(0, len(order), batch_size):
                batch = [labels[i] for i in order[start : start + batch_size]]
                view = ObsView(*(th.cat(x, 0) for x in zip(*(b.view for b in batch), strict=True)))
                task_of, rank, labelled = (th.cat([getattr(b, k) for b in batch], 0) for k in ("task_of", "rank", "labelled"))
                epoch_losses.append(
                    self._step(optimizer, losses.cover_imitation_loss(head, view, task_of, rank, labelled, as_set))
                )
        self.policy.set_training_mode(False)
        return float(np.mean(epoch_losses)) if epoch_losses else float("nan")

    def set_env(self, env: GymEnv, force_reset: bool = True) -> None:
        """Attach an env. With a size-agnostic policy the env may have other entity/task counts (zero-shot transfer):
        the spaces are adopted and the replay buffer is rebuilt for the new sizes. Feature sizes must match."""
        env = self._wrap_env(env, self.verbose)  # type: ignore[arg-type]
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
        buffer = self.counterfactual_buffer
        if buffer is None or buffer.observation_space != new_obs or buffer.n_envs != env.num_envs:
            self.counterfactual_buffer = self._make_counterfactual_buffer()
        elif self.counterfactual_rate > 0:
            self._branchable_envs()

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfTwoStageSAC],
        path: Any,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> SelfTwoStageSAC:
        """Load a model; ``env`` may have other entity/task counts when the policy is size-agnostic (see :meth:`set_env`),
        and another number of envs (a model trained on ``n_envs`` copies loads on one env to evaluate or transfer)."""
        if isinstance(path, str | pathlib.Path):
            check_saved_model(path, ("data", "policy.pth"))
        model = super().load(
            path, env=None, device=device, custom_objects=custom_objects, print_system_info=print_system_info, **kwargs
        )
        if env is not None:
            env = model._wrap_env(env, model.verbose)  # type: ignore[arg-type]
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
        return [
            *super()._excluded_save_params(),
            "actor",
            "critic",
            "critic_target",
            "selector",
            "select_critic",
            "select_critic_target",
            "counterfactual_buffer",
        ]

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
