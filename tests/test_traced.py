"""The losses of a gradient step laid out with fixed shapes (``steps``): the eager losses up to rounding, and one graph
with no break under ``torch.compile``'s tracer, which a captured step (CUDA graphs) needs."""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch as th
import torch._dynamo

import envs  # noqa: F401  (registers the TaskAlloc ids)
from sb3_taskalloc import TwoStageSAC
from sb3_taskalloc.common.torch_layers import ObsView, parse_obs
from sb3_taskalloc.two_stage_sac import losses


@pytest.fixture(scope="module")
def filled() -> tuple[TwoStageSAC, ObsView, th.Tensor, th.Tensor]:
    """RBF with its first 12 robots (the padded loops trace in seconds), the zoo's team search, 48 steps collected;
    16 rows of the replay buffer."""
    env = gym.make("TaskAlloc/RBF-v0", entity_rows=tuple(range(12)))
    model = TwoStageSAC(
        "TAMPolicy", env, learning_starts=48, seed=0, device="cpu", select_kwargs={"search_coef": 30.0, "search_samples": 8}
    )
    with pytest.warns(UserWarning, match="within the warm-up"):
        model.learn(48)  # the warm-up alone: decisions stored, nothing trained
    th.manual_seed(1)
    data = model.replay_buffer.sample(16)
    return model, parse_obs(data.observations), data.candidates, data.pick_rank


def select_losses(model: TwoStageSAC, view: ObsView, cand: th.Tensor, rank: th.Tensor, steps: int | None):
    return losses.select_losses(
        model.selector, model.select_critic, model.select_critic_target, view, cand, rank, True, th.tensor(0.1), 0.5,
        model.policy.selector_prior, 0.5, steps=steps,
    )  # fmt: skip


def test_padded_select_losses_are_the_eager_ones(filled):
    """Padded to N pick steps and weighted, the select stage's losses, targets and temperature loss are the eager ones
    up to rounding; the team search's distillation term, from the same random stream, too."""
    model, view, cand, rank = filled
    N = rank.shape[-1]
    eager, padded = select_losses(model, view, cand, rank, None), select_losses(model, view, cand, rank, N)
    assert eager is not None and padded is not None and padded.weight is not None
    assert eager.n == int(padded.n) > 8
    assert padded.target.shape[0] == N > int(padded.weight.gt(0).any((1, 2)).sum())  # steps after the last pick, weight 0
    th.testing.assert_close(padded.critic_loss, eager.critic_loss)
    th.testing.assert_close(padded.actor_loss, eager.actor_loss)
    th.testing.assert_close(padded.target[padded.weight > 0], eager.target)
    log_alpha = th.tensor([-1.5])
    th.testing.assert_close(
        losses.ent_coef_loss(log_alpha, padded.entropy, padded.target_entropy, padded.weight),
        losses.ent_coef_loss(log_alpha, eager.entropy, eager.target_entropy),
    )
    found = []
    for steps in (None, N):
        th.manual_seed(2)
        found.append(losses.select_search_loss(model.selector, view, cand, 8, 1.0, steps))
    assert found[0].loss != 0 and 0 < found[0].improved < 1  # the search found better teams for some tasks
    for a, b in zip(*found, strict=True):
        th.testing.assert_close(a, b)


def test_padded_select_step_traces_whole(filled):
    """The select stage's losses with the search term, padded, trace as one graph with no break
    (``torch._dynamo.explain``, the tracer of ``torch.compile(fullgraph=True)``); the eager losses do not."""
    model, view, cand, rank = filled
    N = rank.shape[-1]

    def step(view: ObsView, cand: th.Tensor, rank: th.Tensor, steps: int | None) -> tuple[th.Tensor, th.Tensor]:
        select = select_losses(model, view, cand, rank, steps)
        assert select is not None
        search = losses.select_search_loss(model.selector, view, cand, 8, 1.0, steps)
        return select.critic_loss, select.actor_loss + 30.0 * search.loss

    torch._dynamo.reset()
    padded = torch._dynamo.explain(step)(view, cand, rank, N)
    assert padded.graph_count == 1 and padded.graph_break_count == 0, padded.break_reasons
    # The eager losses read their pick count from the tensors: whole-graph tracing stops at that host read (at once,
    # where explain() would trace on through its 40-odd breaks).
    with pytest.raises(torch._dynamo.exc.TorchDynamoException, match="data-dependent"):
        torch.compile(step, fullgraph=True, backend="eager")(view, cand, rank, None)


def test_preassign_losses_trace_whole(filled):
    """Stage 1's losses (target, critic, actor with the critic held constant, temperature over weighted states) trace
    as one graph with no break; the weighted temperature loss is the selected one up to rounding, and the actor loss
    gives the critics no gradient."""
    from sb3_taskalloc.two_stage_sac.updates import PreAssignUpdate, temperature

    model = filled[0]
    th.manual_seed(3)
    data = model.replay_buffer.sample(16)
    view, next_view = parse_obs(data.observations), parse_obs(data.next_observations)
    busy = th.arange(16) < 3  # three states whose entities are all busy: no free entity, no entropy to count
    view = view._replace(entity_mask=view.entity_mask & ~busy.unsqueeze(1))
    update = PreAssignUpdate(model)
    assert model.actor is not None and model.critic is not None and model.log_ent_coef is not None

    def step(view: ObsView, next_view: ObsView, weighted: bool) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        alpha = temperature(model.log_ent_coef, model.ent_coef_tensor)
        critic = update.critic_loss(view, next_view, data, alpha)
        dist = model.actor(view)
        actor = losses.preassign_actor_loss(dist, model.critic, critic.contexts, view, alpha, model.policy.actor_prior, 0.5)
        entropy = losses.preassign_entropy(dist, view, model.target_entropy_ratio, weighted)
        return critic.loss, actor, losses.ent_coef_loss(model.log_ent_coef, entropy.entropy, entropy.target, entropy.weight)

    free = view.assignable.any(1)
    assert 0 < int(free.sum()) == len(free) - 3  # the weights matter
    selected, weighted = step(view, next_view, False), step(view, next_view, True)
    for a, b in zip(selected, weighted, strict=True):
        th.testing.assert_close(a, b)
    model.critic.zero_grad(set_to_none=True)
    selected[1].backward()
    assert all(p.grad is None for p in model.critic.parameters())
    assert any(p.grad is not None and bool(p.grad.any()) for p in model.actor.parameters())
    torch._dynamo.reset()
    explained = torch._dynamo.explain(step)(view, next_view, True)
    assert explained.graph_count == 1 and explained.graph_break_count == 0, explained.break_reasons
