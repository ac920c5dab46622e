"""TAMPolicy: masks, NaN safety, permutation equivariance, padding invariance, its settings and its initial rules (how
it decides: ``test_policy_decisions.py``; its layers: ``test_layers.py``)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.utils import obs_as_tensor

from envs.rendering import random_valid_action
from sb3_taskalloc import TAMPolicy
from sb3_taskalloc.common.torch_layers import parse_obs
from sb3_taskalloc.two_stage_sac.decoding import get_decoding_strategy
from sb3_taskalloc.two_stage_sac.select_stage import SelectState

VARIANTS = {
    "full": {},
    "wo_pre_seq": {"preassign": False},
    "wo_pre_random": {"preassign": False, "task_order": "random"},
    "wo_tam": {"encoder": "mlp"},
    "wo_amix": {"mixer": "global"},
    "attention_monotonic": {"n_attention_layers": 1, "mixer_kwargs": {"monotonic": True}},
    "rounds": {"rounds": 3},
}
ENVS = ["TaskAlloc/Almighty-v0", "TaskAlloc/EPT-v0", "TaskAlloc/RBF-v0", "TaskAlloc/MT-v0"]


def make_policy(env: gym.Env, decoder: str = "argmax", decoder_kwargs: dict | None = None, **kwargs) -> TAMPolicy:
    """A narrow TAMPolicy whose deterministic decisions are decoded by the strategy ``decoder``."""
    space = env.observation_space
    policy = TAMPolicy(space, env.action_space, lambda _: 1e-3, hidden_dim=16, **kwargs)  # type: ignore[arg-type]
    policy.decoder = get_decoding_strategy(decoder, **(decoder_kwargs or {}))
    return policy


def sample_observations(env_id: str, n: int, seed: int = 0) -> list[dict[str, np.ndarray]]:
    env = gym.make(env_id)
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    out = [obs]
    while len(out) < n:
        obs, _, term, trunc, _ = env.step(random_valid_action(obs, rng))
        out.append(obs)
        if term or trunc:
            obs, _ = env.reset(seed=int(rng.integers(1 << 30)))
            out.append(obs)
    return out[:n]


def batch(observations: list[dict[str, np.ndarray]]) -> dict[str, th.Tensor]:
    return obs_as_tensor({k: np.stack([o[k] for o in observations]) for k in observations[0]}, th.device("cpu"))  # type: ignore[return-value]


@pytest.mark.parametrize("env_id", ENVS)
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_actions_respect_masks(env_id, variant):
    th.manual_seed(0)
    env = gym.make(env_id)
    policy = make_policy(env, **VARIANTS[variant])
    observations = sample_observations(env_id, 24)
    view = parse_obs(batch(observations))
    M = env.unwrapped.max_tasks  # type: ignore[attr-defined]
    for deterministic in (True, False):
        for _ in range(3):
            d = policy.decide(view, deterministic=deterministic)
            action = d.env_action.numpy()
            for b, obs in enumerate(observations):
                mask = obs["action_mask"].reshape(len(action[b]), M + 1).astype(bool)
                assert mask[np.arange(len(action[b])), action[b]].all(), "an action broke the mask"
            # Candidates are free entities and open tasks; every kept task is covered by its picks.
            cand = d.candidates.numpy()
            assert not (cand & ~view.entity_mask.numpy()[:, None, :]).any()
            assert not (cand & ~view.task_mask.numpy()[:, :, None]).any()
            picked = (d.pick_rank >= 0) & d.kept.unsqueeze(-1)
            supplied = (picked.float() @ view.supply).numpy()
            assert (supplied >= view.demand.numpy() - 1e-4)[d.kept.numpy()].all()
            # The env accepts the action with no invalid assignment.
    env.reset(seed=0)
    act, _ = policy.predict(observations[0], deterministic=True)
    assert act.shape == env.action_space.shape


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_all_masked_rows_no_nan(variant):
    env = gym.make("TaskAlloc/RBF-v0")
    policy = make_policy(env, **VARIANTS[variant])
    obs = sample_observations("TaskAlloc/RBF-v0", 2)
    no_entities = {k: v.copy() for k, v in obs[0].items()}
    no_entities["entity_mask"][:] = 0
    no_tasks = {k: v.copy() for k, v in obs[1].items()}
    no_tasks["task_mask"][:] = 0
    view = parse_obs(batch([no_entities, no_tasks]))
    d = policy.decide(view, deterministic=False)
    assert (d.env_action == env.unwrapped.max_tasks).all()  # type: ignore[attr-defined]
    if policy.actor is not None and policy.critic is not None:
        dist = policy.actor(view)
        assert th.isfinite(dist.entropy()).all() and th.isfinite(dist.probs).all()
        for q in policy.critic(view, dist.probs):
            assert th.isfinite(q).all()


def permute(obs: dict[str, np.ndarray], perm_e: np.ndarray, perm_t: np.ndarray) -> dict[str, np.ndarray]:
    N, M = len(perm_e), len(perm_t)
    out = dict(obs)
    for key in ("entity_features", "entity_supply", "entity_mask"):
        out[key] = obs[key][perm_e]
    for key in ("task_features", "task_demand", "task_reward", "task_mask"):
        out[key] = obs[key][perm_t]
    out["pair_cost"] = obs["pair_cost"][perm_e][:, perm_t]
    mask = obs["action_mask"].reshape(N, M + 1)
    out["action_mask"] = np.concatenate([mask[perm_e][:, perm_t], mask[perm_e][:, M:]], 1).reshape(-1)
    return out


@pytest.mark.parametrize("kwargs", [{}, {"n_attention_layers": 1}, {"mixer_kwargs": {"monotonic": True}}])
def test_permutation_equivariance(kwargs):
    th.manual_seed(0)
    env = gym.make("TaskAlloc/RBF-v0")
    policy = make_policy(env, **kwargs)
    obs = sample_observations("TaskAlloc/RBF-v0", 12)[-1]
    rng = np.random.default_rng(0)
    pe, pt = rng.permutation(len(obs["entity_mask"])), rng.permutation(len(obs["task_mask"]))
    v1, v2 = parse_obs(batch([obs])), parse_obs(batch([permute(obs, pe, pt)]))
    assert policy.actor is not None and policy.critic is not None
    p1, p2 = policy.actor(v1).probs[0], policy.actor(v2).probs[0]
    th.testing.assert_close(p1[pe][:, pt], p2, atol=1e-5, rtol=1e-5)
    q1 = policy.critic.q_networks[0].scorer(v1)[0]  # type: ignore[index]
    q2 = policy.critic.q_networks[0].scorer(v2)[0]  # type: ignore[index]
    th.testing.assert_close(q1[pe][:, pt], q2, atol=1e-5, rtol=1e-5)
    for a, b in zip(policy.critic(v1, policy.actor(v1).probs), policy.critic(v2, policy.actor(v2).probs), strict=True):
        th.testing.assert_close(a, b, atol=1e-4, rtol=1e-5)  # Q_tot is invariant


def test_padding_changes_nothing():
    th.manual_seed(0)
    small = gym.make("TaskAlloc/RBF-v0")
    big = gym.make("TaskAlloc/RBF-v0", max_entities=140, max_tasks=14)
    policy = make_policy(small, n_attention_layers=1)
    o_small, _ = small.reset(seed=3)
    o_big, _ = big.reset(seed=3)
    v_small, v_big = parse_obs(batch([o_small])), parse_obs(batch([o_big]))
    assert policy.actor is not None and policy.critic is not None
    p_small, p_big = policy.actor(v_small).probs[0], policy.actor(v_big).probs[0]
    th.testing.assert_close(p_big[:100, :10], p_small, atol=1e-5, rtol=1e-5)
    assert p_big[100:].abs().sum() == 0 and p_big[:, 10:].abs().sum() == 0
    for a, b in zip(
        policy.critic(v_small, policy.actor(v_small).probs), policy.critic(v_big, policy.actor(v_big).probs), strict=True
    ):
        th.testing.assert_close(a, b, atol=1e-4, rtol=1e-5)
    # Deterministic decisions agree on the real entities; padded ones stay unassigned.
    a_small = policy.decide(v_small, deterministic=True).env_action[0]
    a_big = policy.decide(v_big, deterministic=True).env_action[0]
    assert th.equal(th.where(a_big[:100] == 14, 10, a_big[:100]), a_small) and (a_big[100:] == 14).all()


def test_bad_spaces_rejected():
    env = gym.make("CartPole-v1")
    with pytest.raises(ValueError, match="TaskAlloc Dict observation space"):
        TAMPolicy(env.observation_space, env.action_space, lambda _: 1e-3)  # type: ignore[arg-type]
    rbf = gym.make("TaskAlloc/RBF-v0")
    with pytest.raises(ValueError, match="encoder"):
        make_policy(rbf, encoder="cnn")
    with pytest.raises(ValueError, match="mixer"):
        make_policy(rbf, mixer="qmix")
    with pytest.raises(ValueError, match="task_order"):
        make_policy(rbf, preassign=False, task_order="shuffled")


def test_options_that_do_not_apply_are_refused():
    """``task_order`` orders the tasks of the shared pool: with pre-assignment there is no order to choose."""
    rbf = gym.make("TaskAlloc/RBF-v0")
    for order in ("sequential", "random"):
        with pytest.raises(ValueError, match="only without pre-assignment"):
            make_policy(rbf, task_order=order)
    assert make_policy(rbf, preassign=False).task_order == "sequential"


@pytest.mark.parametrize(
    ("kwargs", "agnostic"),
    [({}, True), ({"preassign": False}, True), ({"encoder": "mlp"}, False), ({"mixer": "global"}, False)],
)
def test_size_agnostic_is_declared_by_the_components(kwargs, agnostic):
    """The policy is size-agnostic exactly when every component it was built from says so."""
    policy = make_policy(gym.make("TaskAlloc/EPT-v0"), **kwargs)
    assert policy.size_agnostic is agnostic
    modules = [m for m in (policy.actor, policy.critic, policy.selector, policy.select_critic) if m is not None]
    assert all(isinstance(m.size_agnostic, bool) for m in modules)
    assert policy.size_agnostic == all(m.size_agnostic for m in modules)


def test_heuristic_init_follows_the_cost_rules():
    """Untrained (``heuristic_init=True``), the deterministic policy sends every free entity to its cheapest open task
    and every task's pointer picks the candidate with the lowest pair cost per unit of remaining demand covered."""
    th.manual_seed(0)
    env = gym.make("TaskAlloc/RBF-v0")
    policy = make_policy(env)
    assert policy.actor is not None
    checked = 0
    for seed in range(6):
        view = parse_obs(batch([env.reset(seed=seed)[0]]))
        free = view.assignable[0]
        choice = policy.actor(view).get_actions(True)[0]
        cost = view.pair_cost[0].masked_fill(~view.valid[0], th.inf)
        th.testing.assert_close(cost[free, choice[free]], cost[free].min(-1).values)
        task_of = th.where(view.assignable, choice.unsqueeze(0), -1)
        st = SelectState(view, task_of)
        task_state, dyn = st.features()
        head = policy.selector.head
        logits = head(head.embed_entities(view), task_state, dyn, task_of).unsqueeze(1).expand_as(st.seg)
        mask = st.choice_mask()[0]
        unit = (st.pc_own / st.useful[0].clamp_min(1e-6))[0]
        for j in mask.any(-1).nonzero().flatten().tolist():
            pick = int(logits[0, j].masked_fill(~mask[j], -th.inf).argmax())
            assert unit[pick] == pytest.approx(float(unit[mask[j]].min()), rel=1e-5)
            checked += 1
    assert checked >= 3, "too few tasks had a choice to check the pointer"
    plain = make_policy(env, heuristic_init=False)
    assert (plain.selector.head.dyn.weight[0, :-1] != 0).all()  # PyTorch's default init: every feature weighed


def test_rule_weights_set_the_pre_assign_rule(tmp_path):
    """``rule_weights`` replace the rule's weights by feature name: with only the margin weighed, every free entity goes
    to the open task of its largest margin (reward − pair cost); the weights are saved with the model; an unknown
    feature or a rule without the pair term is refused by name."""
    from sb3_taskalloc import TwoStageSAC

    env = gym.make("TaskAlloc/MT-v0")
    policy = make_policy(env, rule_weights={"pair_cost": 0.0, "margin": 1.0})
    assert policy.actor is not None
    for seed in range(3):
        view = parse_obs(batch([env.reset(seed=seed)[0]]))
        free = view.assignable[0]
        choice = policy.actor(view).get_actions(True)[0]
        margin = (view.reward[0].unsqueeze(0) - view.pair_cost[0]).masked_fill(~view.valid[0], -th.inf)
        th.testing.assert_close(margin[free, choice[free]], margin[free].max(-1).values)
    with pytest.raises(ValueError, match="unknown pair features \\['distance'\\]"):
        make_policy(env, rule_weights={"distance": 1.0})
    with pytest.raises(ValueError, match="got heuristic_init=False"):
        make_policy(env, rule_weights={"margin": 1.0}, heuristic_init=False)
    for ablation in ({"encoder": "mlp"}, {"preassign": False}):  # no pair read-out: nothing to set (the table's rows)
        make_policy(env, rule_weights={"margin": 1.0}, **ablation)
    model = TwoStageSAC("TAMPolicy", "TaskAlloc/MT-v0", device="cpu", policy_kwargs={"rule_weights": {"margin": 3.0}})
    model.save(tmp_path / "m.zip")
    loaded = TwoStageSAC.load(tmp_path / "m.zip", device="cpu")
    assert loaded.policy.rule_weights == {"margin": 3.0}
    th.testing.assert_close(loaded.policy.actor_prior.scorer.pair.weight, model.policy.actor_prior.scorer.pair.weight)


def test_heuristic_init_beats_default_init_untrained():
    """The rule-initialised policy allocates far better than PyTorch's default init before any learning (RBF)."""
    env = gym.make("TaskAlloc/RBF-v0")
    returns = {}
    for heuristic in (True, False):
        th.manual_seed(0)
        policy = make_policy(env, heuristic_init=heuristic)
        obs, _ = env.reset(seed=5)
        total = 0.0
        for _ in range(40):
            action = policy.decide(parse_obs(batch([obs])), deterministic=True).env_action[0].numpy()
            obs, reward, *_ = env.step(action)
            total += float(reward)
        returns[heuristic] = total
    assert returns[True] > returns[False] + 10.0, returns


def test_frozen_priors_skip_only_zero_dot_products():
    """The rule-initialised frozen priors skip their dot products (task embeddings identically 0) and score exactly as
    the full computation; priors with non-zero task embeddings (a loaded state, or ``heuristic_init=False``) do not."""
    th.manual_seed(0)
    env = gym.make("TaskAlloc/RBF-v0")
    policy = make_policy(env)
    assert policy.actor_prior is not None
    scorer, head = policy.actor_prior.scorer, policy.selector_prior.head
    assert scorer.skip_dot and head.skip_dot
    assert not policy.actor.scorer.skip_dot and not policy.selector.head.skip_dot  # trained copies always compute
    view = parse_obs(batch(sample_observations("TaskAlloc/RBF-v0", 8, seed=3)))
    task_of = th.where(view.assignable, policy.actor_prior(view).get_actions(True), -1)
    task_state, dyn = SelectState(view, task_of).features()
    fast = (scorer(view), head(head.embed_entities(view), task_state, dyn, task_of))
    assert head.embed_entities(view).shape[-1] == 0  # the entity MLP is not run
    scorer.skip_dot = head.skip_dot = False
    full = (scorer(view), head(head.embed_entities(view), task_state, dyn, task_of))
    for a, b in zip(fast, full, strict=True):
        th.testing.assert_close(a, b, rtol=0, atol=0)
    # A state whose priors have non-zero task embeddings turns the shortcut off when loaded.
    state = dict(policy.state_dict())
    state["actor_prior.scorer.encoder.f_g.2.bias"] = th.ones_like(state["actor_prior.scorer.encoder.f_g.2.bias"])
    state["selector_prior.head.task.2.bias"] = th.ones_like(state["selector_prior.head.task.2.bias"])
    policy.load_state_dict(state)
    assert not policy.actor_prior.scorer.skip_dot and not policy.selector_prior.head.skip_dot
    assert not make_policy(env, heuristic_init=False).selector_prior.head.skip_dot


def test_optimizers_default_to_fused_adam():
    """Adam runs fused unless ``optimizer_kwargs`` picks an implementation or another optimizer is chosen."""
    env = gym.make("TaskAlloc/Almighty-v0")
    policy = make_policy(env)
    assert policy.actor is not None and policy.critic is not None
    for module in (policy.actor, policy.critic, policy.selector, policy.select_critic):
        assert module.optimizer.defaults["fused"] is True
    chosen = make_policy(env, optimizer_kwargs={"foreach": True})
    assert chosen.selector.optimizer.defaults["foreach"] is True and not chosen.selector.optimizer.defaults["fused"]
    assert "fused" not in chosen.optimizer_kwargs  # the user's kwargs are saved unchanged
    sgd = make_policy(env, optimizer_class=th.optim.SGD)
    assert isinstance(sgd.selector.optimizer, th.optim.SGD)


def test_logit_scale_multiplies_the_pre_assign_logits():
    """``logit_scale`` κ: the pre-assign logits are κ times the scores, the argmax is unchanged, sampling is sharper;
    a non-positive κ is refused. The default is κ = 100 (κ_s = 10) for the rule-initialised actors, 1 for a random start
    (the paper's, and the W/o TAM actor, which has no rule)."""
    env = gym.make("TaskAlloc/RBF-v0")
    view = parse_obs(batch(sample_observations("TaskAlloc/RBF-v0", 4)))
    ruled, paper, flat = make_policy(env), make_policy(env, heuristic_init=False), make_policy(env, encoder="mlp")
    assert (ruled.logit_scale, ruled.select_logit_scale) == (100.0, 10.0)
    assert (paper.logit_scale, paper.select_logit_scale) == (1.0, 1.0)
    assert (flat.logit_scale, flat.select_logit_scale) == (1.0, 10.0)  # its pointer starts at the unit-cost rule
    th.manual_seed(0)
    plain = make_policy(env, logit_scale=1.0)
    th.manual_seed(0)
    sharp = make_policy(env, logit_scale=50.0)
    assert plain.actor is not None and sharp.actor is not None
    d1, d50 = plain.actor(view), sharp.actor(view)
    free = view.assignable
    th.testing.assert_close(
        d50.logits[free].masked_fill(~view.valid[free], 0), 50 * d1.logits[free].masked_fill(~view.valid[free], 0)
    )
    assert th.equal(d1.get_actions(True)[free], d50.get_actions(True)[free])
    assert d50.entropy()[free].mean() < d1.entropy()[free].mean()
    for bad in (0.0, -1.0, float("inf")):
        with pytest.raises(ValueError, match="logit_scale"):
            make_policy(env, logit_scale=bad)


@pytest.mark.skipif(not th.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_decisions_are_the_cpus():
    """A deterministic decision of the zoo's RBF policy on CUDA is the CPU's, for a batch of states."""
    from sb3_taskalloc import TwoStageSAC

    policy = TwoStageSAC.from_zoo("TaskAlloc/RBF-v0", seed=0, n_envs=1, device="cpu").policy
    obs = batch(sample_observations("TaskAlloc/RBF-v0", 6, seed=2))
    with th.no_grad():
        on_cpu = policy.decide(policy.parse(policy.obs_to_tensor(obs)[0]), deterministic=True).env_action
        policy.to("cuda")
        on_cuda = policy.decide(policy.parse(policy.obs_to_tensor(obs)[0]), deterministic=True).env_action
    assert on_cuda.is_cuda and th.equal(on_cuda.cpu(), on_cpu)
