"""``make demo``: train TwoStageSAC briefly on a TaskAlloc env with the env's recommended configuration
(:meth:`TwoStageSAC.from_zoo`: its zoo block, SAC steps on 8 envs at once) at a demo's budget, then a few DAgger
iterations of the pointer, and compare the trained policy with the same policy untrained, Greedy and Random on the
same held-out episodes. Writes a learning curve from step 0 (the deterministic return on held-out episodes after the
SAC steps, then on each DAgger iteration's rollouts; the sampled training episodes), the model and a GIF of one
episode."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    from sb3_taskalloc.experiments.budgets import full_env_id

    parser = argparse.ArgumentParser(
        formatter_class=argparse.ArgumentDefaultsHelpFormatter, prog="python -m sb3_taskalloc.demo", description=__doc__
    )
    parser.add_argument("--env", type=full_env_id, default="TaskAlloc/MT-v0", help="environment id")
    parser.add_argument("--steps", type=int, default=600, help="training env steps (all envs together)")
    parser.add_argument("--n-envs", type=int, default=8, help="envs collected at once (one batched decision for all)")
    parser.add_argument("--dagger-iterations", type=int, default=16, help="DAgger iterations of the pointer after SAC")
    parser.add_argument("--dagger-episodes", type=int, default=2, help="episodes rolled out per DAgger iteration")
    parser.add_argument("--eval-episodes", type=int, default=60, help="held-out evaluation episodes of every agent")
    parser.add_argument("--eval-every", type=int, default=300, help="env steps between the curve's evaluations")
    parser.add_argument("--seed", type=int, default=0, help="training seed")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--out", default="demo_out", help="output folder")
    return parser.parse_args(argv)


#: Envs that run side by side in the DAgger rollouts and in the held-out evaluation (one batched decision for all).
ROLLOUT_ENVS, EVAL_ENVS = 2, 60


def dagger_schedule(env_id: str, iterations: int, episodes: int) -> dict[str, Any]:
    """The :class:`~sb3_taskalloc.SelectDAggerCallback` keywords of the demo: the zoo block's DAgger (its loss and
    teacher; the set loss where the block has none) at the demo's budget."""
    from sb3_taskalloc.zoo_config import zoo_dagger

    return {"imitation": "set", **zoo_dagger(env_id), "iterations": iterations, "episodes": episodes}


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    import numpy as np
    import torch as th
    from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    import envs
    from sb3_taskalloc import SelectDAggerCallback, TwoStageSAC
    from sb3_taskalloc.common.utils import writable_folder

    th.set_num_threads(args.threads)
    if args.env not in envs.ENV_SPECS:
        raise SystemExit(f"unknown env {args.env!r}; choose from {sorted(envs.ENV_SPECS)}")
    if args.n_envs < 1 or args.steps < args.n_envs or args.eval_episodes < 1:
        raise SystemExit("--n-envs and --eval-episodes must be >= 1, and --steps >= --n-envs")
    # Checked now, before training, and run below on batched rollouts instead of one env.
    schedule = dagger_schedule(args.env, args.dagger_iterations, args.dagger_episodes)
    dagger = SelectDAggerCallback(**schedule) if args.dagger_iterations else None

    class EpisodeEnds(BaseCallback):
        """(env steps collected so far, return) of each training episode as it ends, in every env (their Monitors)."""

        def __init__(self) -> None:
            super().__init__()
            self.ends: list[tuple[int, float]] = []

        def _on_step(self) -> bool:
            self.ends += [(self.num_timesteps, info["episode"]["r"]) for info in self.locals["infos"] if "episode" in info]
            return True

    out = writable_folder(args.out)  # before training: the model and the report are written at the end
    # The env's recommended configuration at a demo's budget: its zoo block, with a warm-up of a third of the steps; the
    # block's DAgger runs below on batched rollouts, shortened.
    model = TwoStageSAC.from_zoo(args.env, seed=args.seed, n_envs=args.n_envs, learning_starts=args.steps // 3)
    model.zoo_callbacks = []
    model.set_env(make_vec_env(args.env, n_envs=args.n_envs, seed=args.seed, monitor_dir=str(out / "train")))
    untrained = TwoStageSAC.from_zoo(args.env, seed=args.seed, n_envs=1)
    untrained.policy.load_state_dict(model.policy.state_dict())  # the same policy, before training
    # The curve: the deterministic return on held-out episodes (reset seeds disjoint from training), from step 0.
    curve_env = make_vec_env(args.env, n_envs=4, seed=20_000 + args.seed)
    start = float(np.mean(evaluate_policy(model, curve_env, n_eval_episodes=4)[0]))
    curve = EvalCallback(curve_env, eval_freq=max(1, args.eval_every // args.n_envs), n_eval_episodes=4, log_path=str(out),
                         verbose=0)  # fmt: skip
    episodes = EpisodeEnds()
    print(f"training TwoStageSAC on {args.env} (its zoo block): {args.steps} steps on {args.n_envs} envs, then "
          f"{args.dagger_iterations} DAgger iterations of the pointer...")  # fmt: skip
    t0 = time.time()
    model.learn(args.steps, callback=[episodes, curve], progress_bar=True)
    evaluated = zip(curve.evaluations_timesteps, curve.evaluations_results, strict=True)
    points = [(0, start), *((int(t), float(np.mean(r))) for t, r in evaluated)]
    rollouts: list[tuple[int, float]] = []
    if dagger is not None:  # on rollouts of seeds disjoint from the others
        steps = [args.steps]

        def iteration_done(stats: dict[str, float]) -> None:
            steps.append(steps[-1] + int(stats["steps"]))
            rollouts.append((steps[-1], stats["mean_return"]))

        dagger_env = make_vec_env(args.env, n_envs=ROLLOUT_ENVS, seed=50_000 + args.seed)
        model.distill_select(dagger_env, **dagger.kwargs, seed=50_000 + args.seed, progress_bar=True, callback=iteration_done)
    train_s = time.time() - t0
    model.save(out / "two_stage_sac")
    report(args, {"TwoStageSAC": model, "TwoStageSAC untrained": untrained}, train_s, episodes.ends, points, rollouts)


def report(
    args: argparse.Namespace,
    models: dict[str, Any],
    train_s: float,
    ends_: list[tuple[int, float]],
    points: list[tuple[int, float]],
    rollouts: list[tuple[int, float]],
) -> None:
    """Evaluate the trained and the untrained model beside Greedy and Random on the same held-out episodes; write the
    curve, the GIF of one episode and ``results.json``."""
    import gymnasium as gym
    import numpy as np
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    from envs.rendering import save_gif
    from sb3_taskalloc.baselines import GreedyAllocator, RandomAllocator
    from sb3_taskalloc.experiments.plots import plot_learning_curve

    out = Path(args.out)
    agents = {**models, "Greedy": GreedyAllocator(), "Random": RandomAllocator(args.seed)}
    results, returns = {}, {}
    for name, agent in agents.items():
        # The same episodes for every agent: each env's reset seed and episode count are fixed (evaluate_policy)
        eval_env = make_vec_env(args.env, n_envs=min(EVAL_ENVS, args.eval_episodes), seed=10_000 + args.seed)
        which: list[tuple[int, int]] = []  # (env, its episode) of each return, in evaluate_policy's order

        def note(local: dict[str, Any], _: Any, which: list[tuple[int, int]] = which) -> None:
            if local["done"]:  # called just before evaluate_policy records the episode's return
                which.append((local["i"], int(local["episode_counts"][local["i"]])))

        found, _ = evaluate_policy(agent, eval_env, args.eval_episodes, return_episode_rewards=True, callback=note)  # type: ignore[arg-type]
        returns[name] = np.asarray(found, dtype=float)[sorted(range(len(which)), key=which.__getitem__)]  # paired order
        results[name] = (float(np.mean(returns[name])), float(np.std(returns[name])))
    # The paired per-episode gain of the trained policy over each, mean ± standard error.
    paired: dict[str, list[float | None]] = {}
    for what, other in (("untrained", "TwoStageSAC untrained"), ("Greedy", "Greedy")):
        diff = returns["TwoStageSAC"] - returns[other]
        se = float(diff.std(ddof=1) / np.sqrt(diff.size)) if diff.size > 1 else None  # one episode has no spread
        paired[what] = [float(diff.mean()), se]
    trained = f"trained {args.steps} steps + {args.dagger_iterations} DAgger iterations, {train_s:.0f} s"
    print(f"\n{args.env}: return over {args.eval_episodes} held-out episodes ({trained})")
    for name, (mean, std) in results.items():
        print(f"  {name:22s} {mean:9.1f} ± {std:.1f}")
    for what, (gain, se) in paired.items():
        print(f"  trained − {what} per episode: {gain:+.1f}" + (f" ± {se:.1f} (s.e.)" if se is not None else " (one episode)"))
    ends = np.array([t for t, _ in ends_], dtype=float)
    end = rollouts[-1][0] if rollouts else args.steps
    n = args.eval_episodes
    curves: dict[str, list[tuple[int, float]]] = {
        f"held-out, {n} episodes (untrained, trained)": [
            (0, results["TwoStageSAC untrained"][0]),
            (end, results["TwoStageSAC"][0]),
        ],
        "held-out, 4 episodes (during the SAC steps)": points,
    }
    if rollouts:  # DAgger's own rollouts continue the curve, at the env steps they took
        curves[f"DAgger's rollouts ({args.dagger_episodes} training episodes each)"] = rollouts
    png = plot_learning_curve(
        {"TwoStageSAC, sampled (training episodes)": (ends, np.array([r for _, r in ends_], dtype=float))} if ends_ else {},
        out / "learning_curve.png",
        title=f"{args.env}: TwoStageSAC, {args.steps} steps, then {args.dagger_iterations} DAgger iterations",
        baselines={"Greedy": results["Greedy"][0], "untrained policy": results["TwoStageSAC untrained"][0]},
        xlabel="env steps (training, then DAgger's rollouts)",
        points={
            name: (np.array([t for t, _ in xy], dtype=float), np.array([v for _, v in xy])) for name, xy in curves.items()
        },
    )
    model = models["TwoStageSAC"]
    gif, ret = save_gif(gym.make(args.env, render_mode="rgb_array"), model, out / "episode.gif")
    record = {"env": args.env, "steps": args.steps, "n_envs": args.n_envs, "dagger_iterations": args.dagger_iterations,
              "train_seconds": train_s, "eval": results, "eval_curve": points, "dagger_curve": rollouts,
              "gain": paired["untrained"], "over_greedy": paired["Greedy"]}  # fmt: skip
    (out / "results.json").write_text(json.dumps(record, indent=2))
    print(f"wrote {png}, {gif} (episode return {ret:.1f}), {out / 'two_stage_sac.zip'}, {out / 'results.json'}")


if __name__ == "__main__":
    main()
