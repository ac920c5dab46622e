"""TwoStageSAC, discrete soft actor-critic in two stages (paper Algorithm 1), and its policy.

Implementation details of :class:`TwoStageSAC` and :class:`TAMPolicy` (equations; deviations from the paper and the
published code):

1. Stage-1 critics: Q^k_i(s, j) = o_i·q_j (+ a learned term of the pair cost, coverage and margin), k = 1, 2, mixed
   by AMIX: Q^k_tot(s, c) = MLP(ReLU(Σ_i Q^k_i(s, c_i) w_i + b)), with hyper-weights w_i from a self-attention
   hypernetwork over the free entities and a state-dependent hyper-bias b. Target copies updated by Polyak
   averaging (τ). ``TAMPolicy(team_value=True)`` (not in the paper) adds Σ_{j open} g(z_j) on each task's aggregate
   candidate supply share, cost and count (:class:`~sb3_taskalloc.common.mixers.TeamValue`): no per-entity term can
   tell whether a candidate set covers its task.
2. Stage-1 target: y = r + γ(1 − terminated)[min_k AMIX̄^k(Σ_j π_i(j|s') Q̄^k_i(s', j)) + α·H(s')], with
   H(s) = Σ_i H(π_i(·|s)) over free entities (the joint entropy of the factorised policy; ``entropy_bonus="mean"``:
   its mean over the free entities, which does not grow with their number). The env reward is the
   learning signal (the published code regressed internal select returns instead). ``n_steps`` > 1: r is the n-step
   return Σ_{k<n} γ^k r_{t+k} and γ becomes γ^n (fewer at an episode end), s' the state n steps later.
   ``reward_timing="commitment"``: r is the env's commitment reward, the profit of a task (reward − its team's
   charges) credited in the step its committed team covers it instead of when the team arrives (corrected on arrival
   for the decay during travel; same sum over an episode). The critics do not observe committed-but-unpaid tasks, so
   a payment that arrives steps after its decision is otherwise credited to the decisions made just before it.
3. Stage-1 critic loss: ½ Σ_k (AMIX^k(Q^k_i(s, c_i)) − y)²; actor loss: −α·H(s) − min_k AMIX^k(Σ_j π_i(j|s) Q^k_i(s, j))
   (the paper's L_actor and L_critic with the true entropy and the expectation over actions, as in discrete SAC).
   Both losses use the same critic values, computed once before either network steps (as in the original SAC
   code): the actor loss reuses the critics' scores and AMIX context, detached, with the critics frozen, so its
   backward pass never runs through the critic networks.
4. α auto-tuned (``ent_coef="auto"``): loss log α·(H̄(s) − H̄*), H̄ = mean per-entity entropy,
   H̄* = ``target_entropy_ratio`` × mean_i log(#valid tasks of i); or fixed (paper: 0.05).
5. Select stage: a short MDP per task computed from the observation (state = remaining demand and picked set;
   action = pick; reward = −pair cost, + the task reward on covering; γ = 1 within a task), trained by discrete
   SAC: Q^k(s_t, a_t) → r_t + (1 − done_t)·Σ_a π(a|s_{t+1})[min_k Q̄^k(s_{t+1}, a) − α_s log π(a|s_{t+1})];
   actor loss Σ_a π(a|s_t)[α_s log π(a|s_t) − min_k Q^k(s_t, a)]. Transitions are re-derived from the stored
   (observation, candidate sets, pick order); TD targets are detached and use the target critic. Two exact
   prunings (pair costs are non-negative): a candidate that covers none of the remaining demand is not a choice
   (it could only add cost), and a task's decoding stops as soon as it can no longer be kept (``still_winnable``):
   it would be abandoned anyway. See :mod:`~sb3_taskalloc.two_stage_sac.select_stage`.
6. Pointer: logits u_i = d_i·e_j^t/√d + w·x_i^t, a dot-product pointer instead of the paper's additive
   vᵀ tanh(W1 e_j^t + W2 d_i) (same inputs, no batch × entities × hidden tensor per step);
   e_j^t re-encodes the task's remaining demand after t picks (instead of the learned update
   T^{t+1} = T^t + f^a(u^t)); x_i^t = a fixed basis of the entity's coverage of that demand, pair cost, margin,
   waste and unit cost (pair cost per unit of remaining demand covered), weighed linearly. The select critics
   add a per-task baseline b(e_j^t). All tasks of all batch rows decode in parallel. ``select_pair_hidden`` > 0
   adds to the actor's logits an MLP g([x_i^t, s_j^t]) of the entity's basis and its task's state (not in the
   paper): the interactions of the two that the dot product and the linear read-out cannot express, at one
   batch × entities × width tensor per step. ``select_scarcity`` adds two columns to x_i^t (not in the paper): the
   unit cost with each resource k weighed by w_k and by w_k², w_k = (remaining demand of k) / (what the task's
   candidates left offer of k), so that a candidate rich in a resource few others offer ranks first, as in the
   exact cover of the candidates and not in the unit-cost rule.
7. Scores are divided by √d in the actor (paper) and not in the critics. Inputs are symlog-normalised.
8. Warm-up (``learning_starts``): uniformly random valid pre-assignments and picks (``warmup_exploration="uniform"``),
   or samples of the policy itself (``"policy"``: with ``heuristic_init``, the cost-greedy rules), whose transitions
   resemble the deployed behaviour; on RBF uniform decisions send entities across the grid and score about a tenth
   of the rule.
9. Ablations are policy kwargs: ``preassign=False, task_order="sequential"|"random"`` (W/o Pre),
   ``encoder="mlp"`` (W/o TAM), ``mixer="global"`` (W/o AMIX): each names a component of the policy. Without
   pre-assignment, abandoned picks return to the pool.
10. Initialisation (``TAMPolicy(heuristic_init=True)``, not in the paper): the actors start at cost-greedy rules.
   The pre-assign read-out weighs only the symlog pair cost (each entity leans to its cheapest task), the
   pointer's only the symlog unit cost (each task picks the candidate that covers its remaining demand at the
   lowest cost per unit, the rule of :class:`~sb3_taskalloc.baselines.GreedyAllocator`), and the last layer of
   both task embeddings starts at 0, so the dot-product terms start at 0 and grow by learning. Critics keep
   PyTorch's initialisation. ``heuristic_init=False`` is the paper's random start. The rules' temperature is set by
   ``logit_scale`` κ and ``select_logit_scale`` κ_s (both 1 in the paper), which multiply the actors' scores: a
   rule's argmax does not depend on it, its samples do. On RBF one entity's pair costs differ by a few percent between
   tasks, so at κ = 1 the sampled pre-assignment is nearly uniform: sampled episodes score 15 against 135 for the
   argmax on the same seeds, and the critics learn the values of a behaviour that is never deployed. κ = 100,
   κ_s = 10 bring the samples to 107 (ties between equidistant tasks stay random).
11. Critic warm-up (``actor_warmup``): the first gradient steps train only the critics, so the actors start
   learning from critics that have seen the values of their initial rules.
12. Prior term (``prior_coef`` β, ``select_prior_coef`` β_s; not in the paper): each actor loss adds
   β·KL(π ‖ π₀), π₀ = the actor at initialisation (frozen copies ``actor_prior``/``selector_prior`` in the
   policy), as a behaviour prior (the regularised optimum is π ∝ π₀·exp(Q/β) where the entropy term is small).
   The critics' targets keep the entropy bonus of details 2 and 5. With ``heuristic_init`` the actors then
   leave the cost-greedy rules only where the critics' values outweigh the KL, instead of following the noisy
   early critics away from them. The rule-initialised π₀ has
   task embeddings that are identically 0, so its scores are computed without its dot products (``freeze``).
13. Updates: Adam is fused by default (``TAMPolicy._make_optimizer``) and the soft target updates are one
   multi-tensor operation each (:func:`foreach_polyak_update`, SB3's arithmetic): faster, same updates. The TAM
   dot products apply the entity MLP's last layer to the task embeddings instead, h_i·g_j = z_i·(Wᵀg_j) + b·g_j
   (``TAMEncoder.dot``), and the layers that read the raw features reorder their weight-gradient product
   (``NarrowLinear``): the same values and gradients up to rounding, at less cost on a CPU.
14. Exact one-step improvement (``profit_coef`` λ, not in the paper): the step's profit P(c) of a pre-assignment c is
   computable from the observation (decode the teams deterministically, sum r_j − Σ pair costs over the kept tasks:
   the commitment reward before decay). For a few random free entities i of each state the term moves i from its
   argmax task to every open task j, everyone else at the argmax c, and adds λ·(−Σ_j π_i(j|s) A_ij / σ_A),
   A_ij = P(c^{i→j}) − P(c), to the actor loss: a coordinate-wise improvement of the deployed pre-assignment on the
   step's profit (what the per-step MILP maximises exactly), which needs neither sampling nor a critic. The critics'
   term keeps what comes after the step (entities tied up travelling, tasks left for later).
15. Decision rounds (``TAMPolicy(rounds=R)``, not in the paper, where R = 1): a task whose candidates fall short of its
   demand keeps every entity that chose it idle for the step, although other tasks could use them. After each round
   the entities the pointer did not pick pre-assign again, with the same actor and pointer, among the open tasks
   that no round has tried yet (a task's candidates come from one round only), up to R rounds. The losses learn from
   the first round's candidate sets and picks; the reward of the step, and so the stage-1 targets, include the teams
   of the later rounds.
16. Search distillation (``search_coef`` λ_s, not in the paper): per state, the argmax pre-assignment c and K − 1 joint
   pre-assignments sampled from π^(1/T) are decoded deterministically and scored by the step's profit P (detail 14);
   where the best, c*, beats c, the actor loss adds −λ_s·Σ_i log π_i(c*_i|s) over the free entities. Detail 14 and
   the critics' gradient move the argmax one entity at a time; a sample moves many entities at once and finds joint
   changes (a team assembled elsewhere) that no single move improves, which is where the per-step MILP gains over the
   rule. As the argmax improves, so do the samples around it (a policy improvement by search, distilled). The critics'
   term keeps what comes after the step.
17. Counterfactual transitions (``counterfactual_rate`` ρ, not in the paper): at a share ρ of the collection steps every
   env is also deep-copied and the copy takes a second decision c′ sampled at the same state. The copy shares the env's
   random state (arrivals, demand noise), so the two transitions differ by the decision alone; c′'s goes to a buffer of
   its own, and ``counterfactual_batch_size`` of them join each stage-1 minibatch (critic, actor and temperature
   losses) after the replayed rows, as one-step transitions. The actor's gradient follows the critic's differences
   Q(s, c) − Q(s, c′) between decisions of one state, and one sampled decision per state shows the critic few of them:
   its state values track the return while its ranking of the decisions of a state stays near chance (``diagnose``'s
   decision pairs). With ``counterfactual_coef`` λ_c > 0 each branched transition comes with the replayed one of its
   state (the branched buffer is kept row for row beside the replay buffer) and the critic loss adds
   λ_c·½ Σ_k mean((Q^k(s, c) − Q^k(s, c′)) − (y − y′))²: the state's value cancels from the difference, and so does
   most of the targets' noise, since both transitions met the same random draws. The envs must live in the training
   process (``DummyVecEnv``).
18. Select-stage search distillation (``select_search_coef`` λ_p, not in the paper): the select stage's own objective,
   a task's reward on cover minus its team's pair costs, is computable from the observation. For each task of the
   stored first round, the deterministic decode of its team and K − 1 decodes sampled from the pointer at temperature
   T are scored by it; where the best team beats the deterministic one, the pointer's loss adds −λ_p·Σ_t log π(a*_t|s*_t)
   over that team's pick sequence (teacher-forced). The pointer decodes autoregressively, so unlike the factorised
   pre-assignment it can represent a joint choice such as the exact min-cost cover of its candidates; the unit-cost rule
   it starts from spends more (on MT an exact cover of the same candidates returns about a fifth more, on RBF about
   a seventh). ``select_search_method="exact"`` takes that cover itself as the better team: the per-step MILP's
   formulation on the task's candidate pairs (one HiGHS solve per minibatch row), decoded by the pointer among the
   cover's members alone so that the pick order taught is the pointer's own.
19. Select-stage DAgger (:meth:`TwoStageSAC.distill_select`, not in the paper): the exact cover of detail 18 as a
   supervised teacher on the states the deployed policy reaches. Each iteration runs the deterministic policy for a
   number of episodes, labels every decoding round it meets (every pre-assign round of every step) with each task's
   better team of its deterministic decode and the exact cover, and fits the pointer alone, by several passes of Adam
   over every label gathered so far, to −mean over the labelled tasks of Σ_t log π(a*_t|s*_t) (teacher-forced). A task
   whose better team is not kept (profit ≤ 0) is not labelled. Inside ``train`` the same teacher meets the replayed
   states of the sampled behaviour once each, beside the pointer's SAC loss; here it meets the deployed argmax's own
   states (the distribution the deterministic policy is evaluated on) repeatedly, and the pointer fits its labels.
   :class:`.SelectDAggerCallback` runs it when ``learn`` ends (one call, or an rl-zoo3 config's ``callback``).
20. Decision-time team search (``TAMPolicy(select_decision_samples=K_s)``, not in the paper): detail 18's search at
   decision time instead of as a teacher. In a deterministic decision every task of every pre-assign round takes the
   best, by its profit, of the pointer's argmax team and K_s − 1 teams sampled from the pointer at
   ``select_decision_temperature``; all tasks and samples decode in one batched pass. Candidate sets are disjoint,
   so the tasks' best teams together are one decision, never less profitable in the step than the argmax's. With
   ``decision_samples`` (detail 16's decision-time search) the pre-assignment is chosen first, on the argmax teams.
21. Decision-time exact covers (``TAMPolicy(select_decision_exact=True)``, not in the paper): detail 18's exact teacher
   at decision time. Every task of every pre-assign round also weighs the exact most profitable cover of its own
   candidates (the per-step MILP's formulation restricted to the task's candidate pairs, one HiGHS solve per round) and
   sends it where it beats every decoded team. The per-step MILP chooses which entity serves which task and the teams in
   one problem; here the learned pre-assignment chooses the candidates and the solver only the team among them, so the
   two differ exactly by the pre-assignment, and the policy's untrained rule with the same covers measures what
   learning adds to it.
22. Decision-time exact pre-assignment (``TAMPolicy(decision_exact_top=k)``, not in the paper): the pre-assignment
   itself from the solver, pruned by the policy. In a deterministic decision each pre-assign round solves the per-step
   MILP's formulation on the pairs that join each free entity to one of its k most probable tasks under the pre-assign
   actor π; the cover's members are the round's candidates and its teams are weighed as in detail 21. Every entity
   outside the cover stays free for the next round, and the round counts as tried the tasks it covers and those of the
   argmax's candidate sets, as an argmax round does: retrying a task whose nearest entities could not cover it sends
   the leftovers to it again (on MT's untrained rule, first 5 held-out episodes of seeds 0 and 1 with k = 1: 109.2 and
   117.7 against 137.2 and 136.5). With k = 1 the decision is then detail 21's; as k grows toward the number of open
   tasks the round approaches the per-step MILP, whose pairs are all allowed. k is a dial from the learned policy to
   the myopic optimum, and what the policy's pruning adds shows against both ends.
23. Frozen pre-assign actor (``train_preassign_actor=False``, not in the paper): the critics and the select stage learn
   while the pre-assign actor and its temperature keep their initial values (with ``heuristic_init``, the cost-greedy
   rule). The actor follows the critics' differences between the tasks an entity could choose, and on RBF those agree
   in sign with Monte-Carlo differences of the return (``diagnose``'s decision pairs) in 50–57 % of the pairs of four
   five-seed trainings, correlation 0.10–0.18 where the noise of the returns allows 0.70–0.81: its updates move the
   argmax at random. The setting measures what the select stage's learning gives alone, and keeps it where the
   actor's learning does not help.
"""

from sb3_taskalloc.two_stage_sac.callbacks import SelectDAggerCallback
from sb3_taskalloc.two_stage_sac.policies import TAMPolicy
from sb3_taskalloc.two_stage_sac.two_stage_sac import PAPER_KWARGS, TwoStageSAC

__all__ = ["PAPER_KWARGS", "SelectDAggerCallback", "TAMPolicy", "TwoStageSAC"]
