"""``make demo``: train TwoStageSAC briefly on a TaskAlloc env, compare it with greedy and random allocation, write a
learning-curve PNG (the sampled training episodes and SB3's ``EvalCallback`` deterministic evaluations on held-out
episodes, against env steps), the trained model and a GIF of one evaluation episode."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m sb3_taskalloc.demo", description=__doc__)
    parser.add_argument("--env", default="TaskAlloc/RBF-v0", help="environment id")
    parser.add_argument("--steps", type=int, default=1200, help="training env steps")
    parser.add_argument("--eval-episodes", type=int, default=3)
    parser.add_argument("--eval-every", type=int, default=300, help="env steps between deterministic evaluations")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--out", default="demo_out")
    args = parser.parse_args(argv)

    import gymnasium as gym
    import numpy as np
    import torch as th
    from stable_baselines3.common.callbacks import EvalCallback
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.monitor import Monitor

    import envs  # registers the TaskAlloc ids
    from envs.rendering import save_gif
    from sb3_taskalloc import TwoStageSAC
    from sb3_taskalloc.baselines import GreedyAllocator, RandomAllocator
    from sb3_taskalloc.experiments.plots import plot_learning_curve

    th.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.env not in envs.ENV_SPECS:
        raise SystemExit(f"unknown env {args.env!r}; choose from {sorted(envs.ENV_SPECS)}")

    train_env = Monitor(gym.make(args.env), str(out / "train"))
    model = TwoStageSAC("TAMPolicy", train_env, learning_starts=min(300, args.steps // 3), train_freq=2, seed=args.seed)
    print(f"training TwoStageSAC on {args.env} for {args.steps} steps (one gradient step every 2 env steps)...")
    t0 = time.time()
    # Deterministic return on held-out episodes (reset seeds disjoint from training) while training: the sampled
    # training episodes explore, so they score below what the deployed policy does.
    evaluation = EvalCallback(
        make_vec_env(args.env, n_envs=1, seed=20_000 + args.seed),
        eval_freq=args.eval_every,
        n_eval_episodes=args.eval_episodes,
        log_path=str(out),
        deterministic=True,
        verbose=0,
    )
    model.learn(args.steps, callback=evaluation, progress_bar=True)
    train_s = time.time() - t0
    model.save(out / "two_stage_sac")

    results = {}
    for name, agent in (("TwoStageSAC", model), ("Greedy", GreedyAllocator()), ("Random", RandomAllocator(args.seed))):
        eval_env = make_vec_env(args.env, n_envs=1, seed=10_000 + args.seed)  # same evaluation episodes for every agent
        mean, std = evaluate_policy(agent, eval_env, n_eval_episodes=args.eval_episodes, deterministic=True)  # type: ignore[arg-type]
        results[name] = (float(mean), float(std))  # type: ignore[arg-type]
    trained = f"train {args.steps} steps on {model.device}, {train_s:.0f} s"
    print(f"\n{args.env}: return over {args.eval_episodes} evaluation episodes ({trained})")
    for name, (mean, std) in results.items():
        print(f"  {name:12s} {mean:9.2f} ± {std:.2f}")

    returns = np.asarray(train_env.get_episode_rewards(), dtype=float)
    ends = np.cumsum(train_env.get_episode_lengths())
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
