"""Select-stage DAgger (implementation detail 19): the pointer learns the exact most profitable cover of its candidates
on the states the deployed policy reaches. :meth:`.TwoStageSAC.distill_select` runs it; :class:`.SelectDAggerCallback`
runs it when ``learn`` ends.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch as th
from stable_baselines3.common.base_class import maybe_make_env
from stable_baselines3.common.callbacks import ProgressBarCallback
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback
from stable_baselines3.common.vec_env import VecEnv
from tqdm.auto import tqdm

import sb3_taskalloc.two_stage_sac.losses as losses
from sb3_taskalloc.common.torch_layers import ObsView
from sb3_taskalloc.common.utils import check_choices, check_counts, check_finite
from sb3_taskalloc.two_stage_sac.decoding import Decoder, recommended_decoder
from sb3_taskalloc.two_stage_sac.policies import check_spaces
from sb3_taskalloc.two_stage_sac.search import SelectSearchResult, cover_search
from sb3_taskalloc.two_stage_sac.select_stage import SelectState
from sb3_taskalloc.two_stage_sac.updates import optimizer_step

if TYPE_CHECKING:
    from sb3_taskalloc.two_stage_sac.policies import TAMPolicy
    from sb3_taskalloc.two_stage_sac.two_stage_sac import TwoStageSAC


class _CoverLabel(NamedTuple):
    """One decoding round labelled for :meth:`TwoStageSAC.distill_select` (a batch row of one)."""

    view: ObsView
    task_of: th.Tensor  # (1, N) the round's candidate sets
    rank: th.Tensor  # (1, M, N) each task's labelled team in pick order
    labelled: th.Tensor  # (1, M) tasks whose team is a label


class _KeptDecodes(Decoder):
    """The argmax decoder that keeps every round's decode, so that labelling compares the exact cover with the decode
    the rollout made rather than decoding the round again (a third of the labelling's decodes)."""

    def __init__(self) -> None:
        super().__init__()
        self._decodes: list[SelectState] = []

    def teams(self, policy: TAMPolicy, view: ObsView, task_of: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        st = policy.select_round(view, task_of, deterministic=True)
        self._decodes.append(st)
        return st.rank, st.kept()


def _rollout_decision(
    model: TwoStageSAC, view: ObsView, costed: Callable[[ObsView], ObsView] | None
) -> tuple[th.Tensor, list[tuple[ObsView, th.Tensor]], list[SelectSearchResult | None]]:
    """The deterministic policy's decision of a rollout step, its decoding rounds, and per round the decode to weigh the
    exact cover against (:func:`.cover_search`'s ``against``): the rollout's own where the policy decides by the argmax
    and the label is weighed on the pointer's costs, else None (decoded there)."""
    rounds: list[tuple[ObsView, th.Tensor]] = []
    if costed is not None or type(model.policy.decoder) is not Decoder:
        action = model.policy.decide(view, deterministic=True, rounds_out=rounds).env_action
        return action, rounds, [None] * len(rounds)
    kept = _KeptDecodes()
    action = kept.decide(model.policy, view, rounds).env_action
    return action, rounds, [SelectSearchResult.of_decode(st) for st in kept._decodes]


def learn_callbacks(zoo: Sequence[Any], callback: MaybeCallback, progress_bar: bool) -> tuple[MaybeCallback, bool]:
    """``learn``'s callbacks: a :meth:`.TwoStageSAC.from_zoo` model's block callbacks first, then the caller's. Where one
    runs DAgger when training ends (``distills_select``) and a progress bar is asked for (``progress_bar``, or rl-zoo3's
    ``-P``, which adds SB3's bar to the list), DAgger shows its own and SB3's goes just before it, so that it closes
    when the steps end: SB3 closes it after every callback has ended, which leaves it at 100 % through DAgger's minutes.

    :return: the callbacks, and the ``progress_bar`` left for SB3's ``learn`` (False where the bar is placed here)
    """
    given = callback if isinstance(callback, list) else [callback] if callback is not None else []
    callbacks = [*zoo, *given]
    daggers = [c for c in callbacks if getattr(c, "distills_select", False)]
    if not daggers:
        return (callbacks if zoo else callback), progress_bar
    bars = [c for c in callbacks if isinstance(c, ProgressBarCallback)]
    for c in daggers:
        c.progress_bar = progress_bar or bool(bars)
    if not (progress_bar or bars):
        return callbacks, False
    rest = [c for c in callbacks if not isinstance(c, ProgressBarCallback)]
    first = rest.index(daggers[0])
    return [*rest[:first], *(bars or [ProgressBarCallback()]), *rest[first:]], False


def check_distill_select(
    iterations: int,
    episodes: int,
    epochs: int,
    learning_rate: float,
    batch_size: int,
    imitation: str,
    teacher: str | Decoder | None = None,
) -> None:
    """A clear error for the first bad argument of :meth:`TwoStageSAC.distill_select` (named as there), so that a
    schedule that runs it after training (:class:`.SelectDAggerCallback`) can refuse it before training."""
    check_counts({"iterations": iterations, "episodes": episodes, "epochs": epochs, "batch_size": batch_size})
    check_choices({"imitation": (imitation, ("sequence", "set"))})
    check_finite({"learning_rate": learning_rate})
    if not (teacher is None or teacher == "recommended" or callable(getattr(teacher, "costed", None))):
        raise ValueError(
            "teacher must be None (the observation's costs), 'recommended' (the env's recommended decoder's costs) or "
            f"a decoder with a costed() view (exact_top, entity_value), got {teacher!r}"
        )


def teacher_costs(teacher: str | Decoder | None, env_id: str | None) -> Callable[[ObsView], ObsView] | None:
    """The pair costs DAgger's covers are solved and kept under (:func:`distill_select`'s ``teacher``): None for the
    pointer's own (:meth:`.TAMPolicy.select_view`), else the ``costed`` view of the decoder (``"recommended"``:
    ``env_id``'s)."""
    if teacher is None:
        return None
    if teacher == "recommended":
        if env_id is None:
            raise ValueError("teacher='recommended' needs a registered env: its id names the recommended decoder")
        teacher = recommended_decoder(env_id)
    costed = getattr(teacher, "costed", None)
    if not callable(costed):
        raise ValueError(f"teacher {teacher!r} has no costed() view: choose exact_top or entity_value")
    return costed  # type: ignore[no-any-return]


def distill_select(
    model: TwoStageSAC,
    env: GymEnv | str,
    iterations: int = 4,
    episodes: int = 10,
    epochs: int = 8,
    learning_rate: float = 1e-3,
    batch_size: int = 32,
    imitation: str = "sequence",
    teacher: str | Decoder | None = None,
    seed: int | None = None,
    progress_bar: bool = False,
    callback: Callable[[dict[str, float]], bool | None] | None = None,
) -> list[dict[str, float]]:
    """Teach the pointer the exact most profitable cover of its candidates by DAgger (implementation detail 19).

    Each iteration runs the deterministic policy for ``episodes`` episodes on ``env``, labels every decoding round
    it met (every pre-assign round of every step) with each task's better team of its deterministic decode and the
    exact cover of its candidates (:func:`.search.cover_search`), and fits the pointer alone, by
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
    :param teacher: the pair costs the exact covers are solved under and a team must pay by to be a label: None, the
        pointer's own (the observation's, the per-step objective, plus the policy's ``select_values`` if any);
        ``"recommended"``, those of the env's recommended decoder
        (:func:`.decoding.recommended_decoder`: on RBF each pair's cost raised by what the robot gives up,
        ``entity_value``); or a decoder with a ``costed`` view. The pointer still decodes on its own costs, so it
        learns the value-aware teams and needs no values at decision time
    :param seed: seed of the rollouts' env (None: as it comes); use seeds disjoint from the evaluation episodes
    :param progress_bar: show the rollout episodes with tqdm, the iteration beside them
    :param callback: called with each iteration's figures after its fit (an evaluation, a checkpoint); ``False``
        stops DAgger there, as a callback's ``False`` stops ``learn``
    :return: per iteration: the rollouts' mean return and env steps, the rounds met and the tasks labelled, the
        share of the tasks with candidates whose exact cover beats the deterministic team and the mean profit gain
        over those tasks, the last epoch's mean loss
    """
    model.check_distillable()
    check_distill_select(iterations, episodes, epochs, learning_rate, batch_size, imitation, teacher)
    vec_env = model._wrap_env(maybe_make_env(env, model.verbose), model.verbose)
    spec = vec_env.get_attr("spec", indices=0)[0]  # an env id's env carries that id in its spec
    costed = teacher_costs(teacher, None if spec is None else spec.id)
    check_spaces(vec_env.observation_space, vec_env.action_space)
    if vec_env.observation_space != model.observation_space:
        model.policy.check_transfer(vec_env.observation_space)  # type: ignore[arg-type]
    if seed is not None:
        vec_env.seed(seed)
    optimizer = th.optim.Adam(model.policy.selector.head.parameters(), lr=learning_rate)
    rng = np.random.default_rng(seed)
    labels: list[_CoverLabel] = []
    history: list[dict[str, float]] = []
    obs = vec_env.reset()
    with tqdm(total=iterations * episodes, desc="select-stage DAgger", unit="episode", disable=not progress_bar) as bar:
        for it in range(iterations):
            bar.set_postfix_str(f"iteration {it + 1}/{iterations}")
            obs, stats = _label_rollouts(model, vec_env, obs, episodes, labels, bar.update, costed)
            stats["loss"] = _fit_labels(model, labels, optimizer, epochs, batch_size, rng, imitation == "set")
            history.append({"iteration": float(it + 1), **stats})
            if model.verbose >= 1:
                print(f"select-stage DAgger {history[-1]}")
            if callback is not None and callback(history[-1]) is False:
                break
    return history


def _label_rollouts(
    model: TwoStageSAC,
    vec_env: VecEnv,
    obs: Any,
    episodes: int,
    labels: list[_CoverLabel],
    done_episode: Any,
    costed: Callable[[ObsView], ObsView] | None,
) -> tuple[Any, dict[str, float]]:
    """DAgger's data (:meth:`distill_select`): ``episodes`` episodes of the deterministic policy, every decoding
    round labelled with each task's better team of its decode and the exact cover (:func:`.cover_search`), both
    weighed by the teacher's ``costed`` view (None: the pointer's own); each batch row with a labelled task joins
    ``labels`` with the round's view on the pointer's costs (:meth:`.TAMPolicy.select_view`), which it decodes.
    :return: the last observation, and the rollouts' figures"""
    model.policy.set_training_mode(False)
    head = model.policy.selector.head
    returns: list[float] = []
    running = np.zeros(vec_env.num_envs)
    totals = dict.fromkeys(("steps", "rounds", "tasks", "labelled_tasks", "improved", "gain"), 0.0)
    while len(returns) < episodes:
        with th.inference_mode():
            view = model.policy.parse(model.policy.obs_to_tensor(obs)[0])
            action, rounds, decodes = _rollout_decision(model, view, costed)
            for (observed, task_of), decoded in zip(rounds, decodes, strict=True):
                round_view = model.policy.select_view(observed)
                found = cover_search(head, round_view if costed is None else costed(observed), task_of, against=decoded)
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
    model: TwoStageSAC,
    labels: list[_CoverLabel],
    optimizer: th.optim.Optimizer,
    epochs: int,
    batch_size: int,
    rng: np.random.Generator,
    as_set: bool = False,
) -> float:
    """``epochs`` passes of ``optimizer`` over ``labels`` in random minibatches of the pointer's teacher-forced
    log-likelihood (:func:`.losses.cover_imitation_loss`). :return: the last pass's mean loss"""
    head = model.policy.selector.head
    model.policy.set_training_mode(True)
    epoch_losses: list[th.Tensor] = []
    for _ in range(epochs):
        order = rng.permutation(len(labels))
        epoch_losses = []
        for start in range(0, len(order), batch_size):
            batch = [labels[i] for i in order[start : start + batch_size]]
            view = ObsView(*(th.cat(x, 0) for x in zip(*(b.view for b in batch), strict=True)))
            task_of, rank, labelled = (th.cat([getattr(b, k) for b in batch], 0) for k in ("task_of", "rank", "labelled"))
            epoch_losses.append(
                optimizer_step(optimizer, losses.cover_imitation_loss(head, view, task_of, rank, labelled, as_set))
            )
    model.policy.set_training_mode(False)
    return float(np.mean(th.stack(epoch_losses).tolist())) if epoch_losses else float("nan")
