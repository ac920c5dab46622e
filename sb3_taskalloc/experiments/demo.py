"""``make demo``: train TwoStageSAC briefly on a TaskAlloc env (the env's policy settings from its zoo block, SAC steps
on 8 envs at once, then a few DAgger iterations of the pointer), and compare the trained policy with the same policy
untrained, Greedy and Random on the same held-out episodes. Writes a learning curve (from step 0: the deterministic
return on held-out episodes, and the sampled training episodes), the trained model and a GIF of one episode."""

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
    parser.add_argument("--env", type=full_env_id, default="TaskAlloc/RBF-v0", help="environment id")
    parser.add_argument("--steps", type=int, default=3000, help="training env steps (all envs together)")
    parser.add_argument("--n-envs", type=int, default=8, help="envs collected at once (one batched decision for all)")
    parser.add_argument("--dagger-iterations", type=int, default=2, help="DAgger iterations of the pointer after SAC")
    parser.add_argument("--dagger-episodes", type=int, default=2, help="episodes rolled out per DAgger iteration")
    parser.add_argument("--eval-episodes", type=int, default=10, help="held-out evaluation episodes of every agent")
    parser.add_argument("--eval-every", type=int, default=1000, help="env steps between the curve's evaluations")
    parser.add_argument("--seed", type=int, default=0, help="training seed")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--out", default="demo_out", help="output folder")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    import numpy as np
    import torch as th
    from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    import envs  # registers the TaskAlloc ids
    from sb3_taskalloc import SelectDAggerCallback, TwoStageSAC
    from sb3_taskalloc.zoo_config import zoo_hyperparameters

    th.set_num_threads(args.threads)
    if args.env not in envs.ENV_SPECS:
        raise SystemExit(f"unknown env {args.env!r}; choose from {sorted(envs.ENV_SPECS)}")
    if args.n_envs < 1 or args.steps < args.n_envs or min(args.eval_episodes, args.dagger_episodes) < 1:
        raise SystemExit("--n-envs, --eval-episodes and --dagger-episodes must be >= 1, and --steps >= --n-envs")

    class EpisodeEnds(BaseCallback):
        """(env steps collected so far, return) of each training episode as it ends, in every env (their Monitors)."""

        def __init__(self) -> None:
            super().__init__()
            self.ends: list[tuple[int, float]] = []

        def _on_step(self) -> bool:
            self.ends += [(self.num_timesteps, info["episode"]["r"]) for info in self.locals["infos"] if "episode" in info]
            return True

    out = Path(args.out)
    train_env = make_vec_env(args.env, n_envs=args.n_envs, seed=args.seed, monitor_dir=str(out / "train"))
    # The env's policy settings from its zoo block (its pre-assign rule, its decision rounds); the rest are the defaults.
    policy_kwargs = zoo_hyperparameters(args.env).get("policy_kwargs", {})
    model = TwoStageSAC(
        "TAMPolicy", train_env, learning_starts=min(500, args.steps // 3), seed=args.seed, policy_kwargs=policy_kwargs
    )
    untrained = TwoStageSAC("TAMPolicy", args.env, seed=args.seed, policy_kwargs=policy_kwargs)
    untrained.policy.load_state_dict(model.policy.state_dict())  # the same policy, before training
    # The curve: the deterministic return on held-out episodes (reset seeds disjoint from training), from step 0.
    eval_env = make_vec_env(args.env, n_envs=1, seed=20_000 + args.seed)
    start = float(np.mean(evaluate_policy(model, eval_env, n_eval_episodes=min(args.eval_episodes, 3))[0]))
    curve = EvalCallback(
        eval_env,
        eval_freq=max(1, args.eval_every // args.n_envs),
        n_eval_episodes=min(args.eval_episodes, 3),
        log_path=str(out),  # EvalCallback keeps its evaluations only with a log path
        verbose=0,
    )
    dagger = (
        [SelectDAggerCallback(args.dagger_iterations, args.dagger_episodes, imitation="set")] if args.dagger_iterations else []
    )
    episodes = EpisodeEnds()
    print(f"training TwoStageSAC on {args.env}: {args.steps} steps on {args.n_envs} envs, then {args.dagger_iterations} "
          "DAgger iterations of the pointer...")  # fmt: skip
    t0 = time.time()
    model.learn(args.steps, callback=[episodes, curve, *dagger], progress_bar=True)
    train_s = time.time() - t0
    model.save(out / "two_stage_sac")
    evaluated = zip(curve.evaluations_timesteps, curve.evaluations_results, strict=True)
    points = [(0, start), *((int(t), float(np.mean(r))) for t, r in evaluated)]
    report(args, {"TwoStageSAC": model, "TwoStageSAC untrained": untrained}, train_s, episodes.ends, points)


def report(
    args: argparse.Namespace,
    models: dict[str, Any],
    train_s: float,
    ends_: list[tuple[int, float]],
    points: list[tuple[int, float]],
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
        eval_env = make_vec_env(args.env, n_envs=1, seed=10_000 + args.seed)  # the same episodes for every agent
        returns[name], _ = evaluate_policy(agent, eval_env, args.eval_episodes, return_episode_rewards=True)  # type: ignore[arg-type,assignment]
        results[name] = (float(np.mean(returns[name])), float(np.std(returns[name])))
    gain = np.asarray(returns["TwoStageSAC"]) - np.asarray(returns["TwoStageSAC untrained"])
    trained = f"trained {args.steps} steps + {args.dagger_iterations} DAgger iterations, {train_s:.0f} s"
    print(f"\n{args.env}: return over {args.eval_episodes} held-out episodes ({trained})")
    for name, (mean, std) in results.items():
        print(f"  {name:22s} {mean:9.1f} ± {std:.1f}")
    print(f"  trained − untrained per episode: {gain.mean():+.1f} ± {gain.std(ddof=1) / np.sqrt(gain.size):.1f} (s.e.)")
    ends = np.array([t for t, _ in ends_], dtype=float)
    png = plot_learning_curve(
        {"TwoStageSAC, sampled (training episodes)": (ends, np.array([r for _, r in ends_], dtype=float))},
        out / "learning_curve.png",
        title=f"{args.env}: TwoStageSAC, {args.steps} steps",
        baselines={"Greedy": results["Greedy"][0], "untrained policy": results["TwoStageSAC untrained"][0]},
        xlabel="env steps",
        points={
            "TwoStageSAC, deterministic (held-out evaluation)": (
                np.array([t for t, _ in points], dtype=float),
                np.array([v for _, v in points]),
            )
        },
    )
    model = models["TwoStageSAC"]
    gif, ret = save_gif(gym.make(args.env, render_mode="rgb_array"), model, out / "episode.gif")
    record = {"env": args.env, "steps": args.steps, "n_envs": args.n_envs, "dagger_iterations": args.dagger_iterations,
              "train_seconds": train_s, "eval": results, "eval_curve": points}  # fmt: skip
    (out / "results.json").write_text(json.dumps(record, indent=2))
    print(f"wrote {png}, {gif} (episode return {ret:.1f}), {out / 'two_stage_sac.zip'}, {out / 'results.json'}")


if __name__ == "__main__":
    main()
