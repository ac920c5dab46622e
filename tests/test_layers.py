"""The policy's scoring layers against their definitions: the pre-assign scorer's dot product, the narrow linear layer and
the pointer's scores."""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch as th

from sb3_taskalloc.common.torch_layers import parse_obs
from sb3_taskalloc.two_stage_sac.select_stage import SelectState, select_features
from tests.test_policies import batch, make_policy, sample_observations


@pytest.mark.parametrize("n_attention_layers", [0, 1])
def test_scorer_dot_product_equals_its_definition(n_attention_layers):
    """``TAMEncoder.dot`` (the entity MLP's last layer moved to the task side) equals h_i·g_j / scale computed from the
    embeddings, in value and in every parameter's gradient."""
    th.manual_seed(0)
    env = gym.make("TaskAlloc/RBF-v0")
    policy = make_policy(env, n_attention_layers=n_attention_layers, heuristic_init=False)
    assert policy.actor is not None
    encoder, scale = policy.actor.scorer.encoder, policy.actor.scorer.scale
    view = parse_obs(batch(sample_observations("TaskAlloc/RBF-v0", 6, seed=1)))
    weights = th.randn(view.pair_cost.shape, dtype=th.float64)

    def value_and_grads(fn):
        encoder.zero_grad()
        out = fn()
        (out.double() * weights).sum().backward()
        return out.detach(), [p.grad.clone() for p in encoder.parameters()]

    def reference():
        h, g = encoder(view)
        return h @ g.transpose(1, 2) / scale

    fast, fast_grads = value_and_grads(lambda: encoder.dot(view, scale))
    ref, ref_grads = value_and_grads(reference)
    th.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-5)
    for a, b in zip(fast_grads, ref_grads, strict=True):
        th.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


def test_narrow_linear_matches_linear():
    """``NarrowLinear`` (narrow inputs, reordered weight-gradient product) is ``nn.Linear`` in value and gradients, is
    what the MLPs use for the raw features, and keeps the state-dict keys."""
    from sb3_taskalloc.common.torch_layers import NarrowLinear, linear, mlp

    th.manual_seed(0)
    fast = NarrowLinear(8, 64)
    ref = th.nn.Linear(8, 64)
    ref.load_state_dict(fast.state_dict())
    x = th.randn(4, 300, 8)  # 1,200 rows: at least NarrowLinear.min_rows, so the reordered product is used
    assert NarrowLinear.min_rows <= 1200 and "NarrowInputLinear" in type(fast(x).grad_fn).__name__
    assert "NarrowInputLinear" not in type(fast(x[:1, :10]).grad_fn).__name__  # few rows: the plain layer
    grads = []
    for layer in (fast, ref):
        xi = x.clone().requires_grad_(True)
        (layer(xi) ** 2).sum().backward()
        grads.append((layer(x), xi.grad, layer.weight.grad, layer.bias.grad))
    for a, b in zip(*grads, strict=True):
        th.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    with th.no_grad():
        th.testing.assert_close(fast(x), ref(x))
    assert isinstance(mlp(8, 64, 64)[0], NarrowLinear) and type(mlp(64, 64, 64)[0]) is th.nn.Linear
    assert type(linear(7, 1)) is th.nn.Linear  # one output: nothing to gain
    assert list(fast.state_dict()) == ["weight", "bias"]


@pytest.mark.parametrize("state_value", [False, True])
def test_pointer_scores_equal_their_definition(state_value):
    """``PointerHead`` (one batched product over all tasks, then each entity's own column) scores
    u_i = d_i·e_j^t / √d + w·x_i^t (+ b(e_j^t)) with d = entity MLP, e = task MLP, s_j^t the task state, x_i^t the
    basis, as defined, in value and in every parameter's gradient."""
    from sb3_taskalloc.common.torch_layers import SELECT_DYN, PointerHead

    th.manual_seed(0)
    view = parse_obs(batch(sample_observations("TaskAlloc/RBF-v0", 5, seed=2)))
    head = PointerHead(view.entity.shape[-1], view.supply.shape[-1], 16, state_value=state_value)
    task_of = th.where(view.assignable, th.randint(0, view.task_mask.shape[1], view.entity_mask.shape), -1)
    st = SelectState(view, task_of)
    task_state, dyn = select_features(
        view,
        task_of,
        st.pc_own,
        st.rem.expand(3, -1, -1, -1),
        st.cost.expand(3, -1, -1),
        st.npick.expand(3, -1, -1),
    )
    weights = th.randn(3, *task_of.shape, dtype=th.float64)
    own = task_of.clamp_min(0)
    assert dyn.shape[-1] == head.dyn.in_features == SELECT_DYN

    def reference():
        d, e = head.entity(view.entity), head.task(task_state)  # (B, N, H), (T, B, M, H)
        e_own = th.stack([e[:, b, own[b]] for b in range(own.shape[0])], 1)  # (T, B, N, H)
        scores = (e_own * d).sum(-1) / head.scale + head.dyn(dyn).squeeze(-1)
        if head.value is not None:
            scores = scores + th.gather(head.value(e).squeeze(-1), -1, own.expand(3, -1, -1))
        return scores

    results = []
    for fn in (lambda: head(head.embed_entities(view), task_state, dyn, task_of), reference):
        head.zero_grad()
        out = fn()
        (out.double() * weights).sum().backward()
        results.append((out.detach(), [p.grad.clone() for p in head.parameters() if p.grad is not None]))
    (fast, fast_grads), (ref, ref_grads) = results
    assert fast.shape == (3, *task_of.shape)
    th.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-5)
    assert len(fast_grads) == len(ref_grads) == len(list(head.parameters()))
    for a, b in zip(fast_grads, ref_grads, strict=True):
        th.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    # Three consecutive copies of each row share its entity embeddings: the scores of the embeddings repeated.
    with th.no_grad():
        d, copied = head.embed_entities(view), (task_state.repeat_interleave(3, 1), dyn.repeat_interleave(3, 1))
        shared = head(d, *copied, task_of.repeat_interleave(3, 0))
        th.testing.assert_close(shared, head(d.repeat_interleave(3, 0), *copied, task_of.repeat_interleave(3, 0)))
        th.testing.assert_close(shared[:, ::3], fast)
