"""``make demo``: train TwoStageSAC briefly on a TaskAlloc env, compare it with greedy and random allocation, write a
learning-curve PNG (the sampled training episodes and SB3's ``EvalCallback`` deterministic evaluations on held-out
episodes, against env steps), the trained model and a GIF of one evaluation episode."""

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
    parser.add_argument("--steps", type=int, default=4000, help="training env steps (all envs together)")
    parser.add_argument("--n-envs", type=int, default=8, help="envs collected at once (one batched decision for all)")
    parser.add_argument("--eval-episodes", type=int, default=3, help="held-out evaluation episodes")
    parser.add_argument("--eval-every", type=int, default=1000, help="env steps between deterministic evaluations")
    parser.add_argument("--seed", type=int, default=0, help="training seed")
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--out", default="demo_out", help="output folder")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    import torch as th
    from stable_baselines3.common.callbacks import BaseCallback, EvalCallback
    from stable_baselines3.common.env_util import make_vec_env

    import envs  # registers the TaskAlloc ids
    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.zoo_config import zoo_hyperparameters

    th.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.env not in envs.ENV_SPECS:
        raise SystemExit(f"unknown env {args.env!r}; choose from {sorted(envs.ENV_SPECS)}")
    if args.n_envs < 1 or args.steps < args.n_envs:
        raise SystemExit(f"--n-envs must be >= 1 and --steps >= --n-envs, got {args.n_envs} and {args.steps}")

    class EpisodeEnds(BaseCallback):
        """(env steps collected so far, return) of each training episode as it ends, in every env (their Monitors)."""

        def __init__(self) -> None:
            super().__init__()
            self.ends: list[tuple[int, float]] = []

        def _on_step(self) -> bool:
            self.ends += [(self.num_timesteps, info["episode"]["r"]) for info in self.locals["infos"] if "episode" in info]
            return True

    train_env = make_vec_env(args.env, n_envs=args.n_envs, seed=args.seed, monitor_dir=str(out / "train"))
    # The env's policy settings from its zoo block (its pre-assign rule, its decision rounds); the rest are the defaults.
    policy_kwargs = zoo_hyperparameters(args.env).get("policy_kwargs", {})
    model = TwoStageSAC(
        "TAMPolicy", train_env, learning_starts=min(500, args.steps // 3), seed=args.seed, policy_kwargs=policy_kwargs
    )
    print(f"training TwoStageSAC on {args.env} for {args.steps} steps on {args.n_envs} envs (one gradient step per batch)...")
    t0 = time.time()
    # Deterministic return on held-out episodes (reset seeds disjoint from training) while training: the sampled
    # training episodes explore, so they score below what the deployed policy does. EvalCallback counts calls, each
    # of which collects n_envs env steps.
    episodes = EpisodeEnds()
    evaluation = EvalCallback(
        make_vec_env(args.env, n_envs=1, seed=20_000 + args.seed),
        eval_freq=max(1, args.eval_every // args.n_envs),
        n_eval_episodes=args.eval_episodes,
        log_path=str(out),
        deterministic=True,
        verbose=0,
    )
    model.learn(args.steps, callback=[episodes, evaluation], progress_bar=True)
    train_s = time.time() - t0
    model.save(out / "two_stage_sac")
    report(args, model, train_s, episodes.ends, evaluation)


def report(args: argparse.Namespace, model: Any, train_s: float, ends_: list[tuple[int, float]], evaluation: Any) -> None:
    """Evaluate the trained model beside Greedy and Random on the same held-out episodes; write the curve, the GIF of
    one episode and ``results.json``."""
    import gymnasium as gym
    import numpy as np
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    from envs.rendering import save_gif
    from sb3_taskalloc.baselines import GreedyAllocator, RandomAllocator
    from sb3_taskalloc.experiments.plots import plot_learning_curve

    out = Path(args.out)
    results = {}
    for name, agent in (("TwoStageSAC", model), ("Greedy", GreedyAllocator()), ("Random", RandomAllocator(args.seed))):
        eval_env = make_vec_env(args.env, n_envs=1, seed=10_000 + args.seed)  # same evaluation episodes for every agent
        mean, std = evaluate_policy(agent, eval_env, n_eval_episodes=args.eval_episodes, deterministic=True)  # type: ignore[arg-type]
        results[name] = (float(mean), float(std))  # type: ignore[arg-type]
    trained = f"train {args.steps} steps on {model.device}, {train_s:.0f} s"
    print(f"\n{args.env}: return over {args.eval_episodes} evaluation episodes ({trained})")
    for name, (mean, std) in results.items():
        print(f"  {name:12s} {mean:9.2f} ± {std:.2f}")

    ends = np.array([t for t, _ in ends_], dtype=float)
    returns = np.array([r for _, r in ends_], dtype=float)
    png = plot_learning_curve(
        {"TwoStageSAC, sampled (training episodes)": (ends, returns)},
        out / "learning_curve.png",
        title=f"{args.env}: TwoStageSAC, {args.steps} steps",
        baselines={"Greedy": results["Greedy"][0], "Random": results["Random"][0]},
        xlabel="env steps",
        points={
            "TwoStageSAC, deterministic (held-out evaluation)": (
                np.asarray(evaluation.evaluations_timesteps),
                np.asarray(evaluation.evaluations_results, dtype=float).mean(axis=1)
                if evaluation.evaluations_results
                else np.array([]),
            )
        },
    )
    gif, ret = save_gif(
        gym.make(args.env, render_mode="rgb_array"), lambda o: model.predict(o, deterministic=True)[0], out / "episode.gif"
    )
    (out / "results.json").write_text(
        json.dumps(
            {
                "env": args.env,
                "steps": args.steps,
                "n_envs": args.n_envs,
                "device": str(model.device),
                "train_seconds": train_s,
                "eval": results,
                "eval_curve": [
                    [int(t), float(np.mean(r))]
                    for t, r in zip(evaluation.evaluations_timesteps, evaluation.evaluations_results, strict=True)
                ],
            },
            indent=2,
        )
    )
    print(f"wrote {png}, {gif} (episode return {ret:.2f}), {out / 'two_stage_sac.zip'}, {out / 'results.json'}")


if __name__ == "__main__":
    main()
