"""The pointer's teachers: the team search distilled in training, DAgger on each task's exact cover, and the cover's
imitation loss as a sequence and as a set."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_taskalloc import TwoStageSAC
from sb3_taskalloc.common.torch_layers import NEG, ObsView
from sb3_taskalloc.two_stage_sac import losses
from sb3_taskalloc.two_stage_sac.search import cover_search, select_search
from sb3_taskalloc.two_stage_sac.select_stage import SelectState, teacher_forced


def reset_view(model: TwoStageSAC, env_id: str, n: int) -> ObsView:
    """The first observations of reset seeds 0 .. n − 1 of ``env_id``, parsed by ``model``'s policy as one batch."""
    env = gym.make(env_id)
    obs = [env.reset(seed=s)[0] for s in range(n)]
    return model.policy.parse(model.policy.obs_to_tensor({k: np.stack([o[k] for o in obs]) for k in obs[0]})[0])


def mt_argmax_round() -> tuple[TwoStageSAC, ObsView, th.Tensor]:
    """A small untrained MT model, 8 reset states and its argmax pre-assignment ``task_of`` on them."""
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/MT-v0", seed=0, device="cpu", policy_kwargs={"hidden_dim": 16})
    view = reset_view(model, "TaskAlloc/MT-v0", 8)
    with th.no_grad():
        return model, view, th.where(view.assignable, model.actor(view).get_actions(True), -1)


def forced_steps(head, view: ObsView, task_of: th.Tensor, rank: th.Tensor):
    """Step a :class:`SelectState` through the picks of ``rank`` (B, M, N) one at a time, the reference of the
    teacher-forced losses: yields, per step t while a task is active, (t, the state before the step's picks, the
    pointer's masked logits (B, M, N), each task's pick (B, M), which tasks pick (B, M))."""
    st, d = SelectState(view, task_of), head.embed_entities(view)
    for t in range(rank.shape[-1]):
        if not bool(st.active.any()):
            break
        task_state, dyn = st.features()
        logits = head(d, task_state, dyn, task_of).unsqueeze(1).masked_fill(~st.choice_mask(), NEG)
        hit = rank == t
        picks, valid = hit.float().argmax(-1), hit.any(-1) & st.active
        yield t, st, logits, picks, valid
        st.advance(picks, valid)


def test_select_search_loss_distils_the_best_team():
    """``select_kwargs["search_coef"]`` (implementation detail 18): per task, the search's team is at least as
    profitable as the
    deterministic one, its teacher-forced rewards add up to that profit, and the loss is −Σ_t log π(a*_t|s*_t) over the
    tasks it improves, recomputed here by stepping a :class:`SelectState` through the forced picks one at a time."""
    model, view, task_of = mt_argmax_round()
    head = model.selector.head
    B, _, M = view.pair_cost.shape
    candidates = task_of.unsqueeze(1) == th.arange(M).view(1, M, 1)
    th.manual_seed(0)
    found = select_search(head, view, task_of, samples=32, temperature=3.0)
    th.manual_seed(0)
    search = losses.select_search_loss(model.selector, view, candidates, samples=32, temperature=3.0)
    improved = found.profit > found.base
    assert bool(improved.any()), "no sampled team beat the deterministic one: the case checks nothing"
    assert bool((found.profit >= found.base).all())
    assert bool(((found.rank >= 0) <= candidates).all())  # a task picks among its own candidates only
    tf = teacher_forced(view, task_of, found.rank)
    assert tf is not None
    th.testing.assert_close(tf.reward.sum(0)[improved], found.profit[improved], atol=1e-4, rtol=1e-5)
    log_p = th.zeros(B, M)
    for _, _, logits, picks, valid in forced_steps(head, view, task_of, found.rank):
        log_p = log_p + th.where(valid, th.log_softmax(logits, -1).gather(-1, picks.unsqueeze(-1)).squeeze(-1), 0.0)
    th.testing.assert_close(search.loss, -log_p[improved].mean(), atol=1e-4, rtol=1e-5)
    has = candidates.any(-1) & view.task_mask
    assert float(search.improved) == pytest.approx(float(improved[has].float().mean()))
    assert float(search.gain) == pytest.approx(float((found.profit - found.base)[has].mean()), abs=1e-4)
    search.loss.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.selector.parameters())
    one = select_search(head, view, task_of, samples=1, temperature=3.0)
    assert bool((one.profit == one.base).all())
    assert float(losses.select_search_loss(model.selector, view, candidates, samples=1, temperature=3.0).loss) == 0.0
    bad_kwargs = ({"search_coef": -1.0}, {"search_temperature": 0.0}, {"search_samples": 0}, {"search": 1})
    for bad in bad_kwargs:
        with pytest.raises(ValueError, match=next(iter(bad))):
            TwoStageSAC("TAMPolicy", "TaskAlloc/Almighty-v0", select_kwargs=bad)
    with pytest.raises(ValueError, match="pre-assigning policy"):
        TwoStageSAC(
            "TAMPolicy", "TaskAlloc/Almighty-v0", select_kwargs={"search_coef": 1.0}, policy_kwargs={"preassign": False}
        )
    # The term runs inside training and its statistics reach the logger.
    model = TwoStageSAC(
        "TAMPolicy", "TaskAlloc/MT-v0", select_kwargs={"search_coef": 1.0, "search_samples": 4, "batch_size": 4},
        learning_starts=30, batch_size=8, seed=0, device="cpu", policy_kwargs={"hidden_dim": 16},
    )  # fmt: skip
    model.learn(60)
    model.train(gradient_steps=1, batch_size=8)
    assert "train/select_search_improved" in model.logger.name_to_value


def test_distill_select_teaches_the_pointer_the_exact_cover():
    """:meth:`TwoStageSAC.distill_select` (implementation detail 19): its loss is −mean over the labelled tasks of the
    teacher-forced log-likelihood of their teams; DAgger fits the pointer alone, raising the likelihood of the exact
    covers of the rounds the deterministic policy meets, and is reproducible under a seed."""
    env_id = "TaskAlloc/Almighty-v0"

    def new_model() -> TwoStageSAC:
        return TwoStageSAC("TAMPolicy", env_id, seed=0, device="cpu", policy_kwargs={"hidden_dim": 16})

    model = new_model()
    view = reset_view(model, env_id, 8)
    head = model.selector.head
    rounds: list[tuple[ObsView, th.Tensor]] = []
    with th.no_grad():
        model.policy.decide(view, deterministic=True, rounds_out=rounds)
        round_view, task_of = rounds[0]
        found = cover_search(head, round_view, task_of)
    M = found.profit.shape[1]
    labelled = (task_of.unsqueeze(1) == th.arange(M).view(1, M, 1)).any(-1) & (found.profit > 0)
    assert bool(labelled.any()), "no task labelled: the case checks nothing"
    log_p = losses.team_log_prob(head, round_view, task_of, found.rank)
    assert log_p is not None
    before = losses.cover_imitation_loss(head, round_view, task_of, found.rank, labelled)
    th.testing.assert_close(before, -log_p[labelled].mean())
    assert float(losses.cover_imitation_loss(head, round_view, task_of, found.rank, th.zeros_like(labelled))) == 0.0
    frozen = {n: p.detach().clone() for n, p in model.policy.named_parameters() if not n.startswith("selector.")}
    pointer = {n: p.detach().clone() for n, p in model.policy.named_parameters() if n.startswith("selector.")}
    history = model.distill_select(env_id, iterations=2, episodes=8, epochs=4, seed=0)
    assert [h["iteration"] for h in history] == [1.0, 2.0]
    for h in history:
        assert h["steps"] == 8 and h["rounds"] >= 8 and h["labelled_tasks"] > 0 and 0.0 <= h["improved"] <= 1.0
        assert h["gain"] >= -1e-6 and math.isfinite(h["loss"])  # the cover is never worse than the decode
    for name, p in model.policy.named_parameters():
        if name in frozen:
            assert th.equal(p, frozen[name]), f"{name} changed: only the pointer learns"
    assert any(not th.equal(p, pointer[n]) for n, p in model.policy.named_parameters() if n in pointer)
    after = losses.cover_imitation_loss(head, round_view, task_of, found.rank, labelled)
    assert float(after.detach()) < float(before.detach())
    assert new_model().distill_select(env_id, iterations=2, episodes=8, epochs=4, seed=0) == history
    seen: list[dict[str, float]] = []

    def stop_after_one(stats: dict[str, float]) -> bool:  # a callback sees each iteration's figures; False stops there
        seen.append(stats)
        return False

    stopped = new_model().distill_select(env_id, iterations=3, episodes=8, epochs=4, seed=0, callback=stop_after_one)
    assert stopped == seen == history[:1]
    assert len(new_model().distill_select(env_id, iterations=1, episodes=4, epochs=2, imitation="set", seed=0)) == 1
    # On a VecEnv the copies decide in one batch; episodes are counted over all of them.
    (vec,) = new_model().distill_select(make_vec_env(env_id, n_envs=3), iterations=1, episodes=4, epochs=1, seed=0)
    assert vec["steps"] == 6 and vec["rounds"] >= 6  # two batched steps of 3 one-step episodes
    bad_arguments = ({"iterations": 0}, {"episodes": 0}, {"epochs": 1.5}, {"batch_size": 0}, {"learning_rate": 0.0})
    for bad in (*bad_arguments, {"imitation": "team"}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            model.distill_select(env_id, **bad)  # type: ignore[arg-type]
    pooled = TwoStageSAC("TAMPolicy", env_id, device="cpu", policy_kwargs={"preassign": False, "hidden_dim": 16})
    with pytest.raises(ValueError, match="pre-assigning policy"):
        pooled.distill_select(env_id)


def test_cover_imitation_loss_as_a_set():
    """``imitation="set"``: at each step of the labelled order the loss takes the probability of picking any member of
    the cover not picked yet, recomputed here by stepping a :class:`SelectState` through the labelled picks; it is never
    above the sequence loss, which takes the labelled pick's own probability."""
    model, round_view, task_of = mt_argmax_round()
    head = model.selector.head
    B, _, M = round_view.pair_cost.shape
    with th.no_grad():
        found = cover_search(head, round_view, task_of)
    labelled = (task_of.unsqueeze(1) == th.arange(M).view(1, M, 1)).any(-1) & (found.profit > 0)
    assert bool((((found.rank >= 0).sum(-1) > 1) & labelled).any()), "no labelled team of two or more: the set is the pick"
    before = losses.cover_imitation_loss(head, round_view, task_of, found.rank, labelled)
    # As a set: at each step of the labelled order, the probability of any member not picked yet, recomputed by stepping
    # a SelectState through the labelled picks; never below the labelled pick's own probability.
    as_set = losses.cover_imitation_loss(head, round_view, task_of, found.rank, labelled, as_set=True)
    set_log_p = th.zeros(B, M)
    for t, st, logits, _, valid in forced_steps(head, round_view, task_of, found.rank):
        remaining = (found.rank >= t) & st.choice_mask()
        p_set = (th.softmax(logits, -1) * remaining.float()).sum(-1)
        set_log_p = set_log_p + th.where(valid, p_set.clamp_min(1e-12).log(), 0.0)
    th.testing.assert_close(as_set, -set_log_p[labelled].mean(), atol=1e-4, rtol=1e-5)
    assert float(as_set.detach()) <= float(before.detach()) + 1e-6
    assert float(losses.cover_imitation_loss(head, round_view, task_of, found.rank, th.zeros_like(labelled), True)) == 0.0


def test_distill_select_weighs_the_cover_against_the_rollouts_own_decode():
    """Labelling compares each round's exact cover with the decode the rollout made (the argmax decoder keeps it)
    instead of decoding the round again: the kept decodes equal fresh decodes of the recorded rounds, and DAgger's
    figures and pointer equal those of a run that decodes every round again (a decoder of the same decisions that is
    not the argmax class itself)."""
    from sb3_taskalloc.two_stage_sac.dagger import _rollout_decision
    from sb3_taskalloc.two_stage_sac.decoding import Decoder
    from sb3_taskalloc.two_stage_sac.select_stage import decode_round, task_profit

    env_id = "TaskAlloc/Almighty-v0"

    def new_model() -> TwoStageSAC:
        return TwoStageSAC("TAMPolicy", env_id, seed=0, device="cpu", policy_kwargs={"hidden_dim": 16, "rounds": 2})

    model = new_model()
    view = reset_view(model, env_id, 6)
    with th.inference_mode():
        action, rounds, decodes = _rollout_decision(model, view, None)
        assert th.equal(action, model.policy.decide(view, deterministic=True).env_action)
        assert len(rounds) == len(decodes) == 2
        for (observed, task_of), kept in zip(rounds, decodes, strict=True):
            assert kept is not None
            fresh = decode_round(model.selector.head, model.policy.select_view(observed), task_of, deterministic=True)
            assert th.equal(kept.rank, fresh.rank) and th.equal(kept.profit, task_profit(fresh))
        assert all(d is None for d in _rollout_decision(model, view, lambda v: v)[2])  # a teacher's costs: decoded there

    class SameArgmax(Decoder):
        pass

    dagger = {"iterations": 2, "episodes": 6, "epochs": 2, "seed": 0}
    kept_model, again = new_model(), new_model()
    again.set_decoder(SameArgmax())
    history = kept_model.distill_select(env_id, **dagger)
    assert history[0]["labelled_tasks"] > 0 and again.distill_select(env_id, **dagger) == history
    pairs = zip(kept_model.policy.selector.state_dict().items(), again.policy.selector.state_dict().values(), strict=True)
    for (name, p), q in pairs:
        assert th.equal(p, q), name
