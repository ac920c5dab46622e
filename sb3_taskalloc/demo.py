"""``make demo``: one RBF episode with random valid allocations, its return, and a GIF of the episode."""

from __future__ import annotations

import argparse
from pathlib import Path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m sb3_taskalloc.demo", description=__doc__)
    parser.add_argument("--env", default="TaskAlloc/RBF-v0")
    parser.add_argument("--out", default="demo_out")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    import gymnasium as gym

    import envs  # noqa: F401  (registers the ids)
    from envs.rendering import save_gif

    out = Path(args.out)
    env = gym.make(args.env, render_mode="rgb_array")
    path, ret = save_gif(env, None, out / "random_episode.gif", seed=args.seed)
    print(f"{args.env}: random valid allocations, seed {args.seed}: return {ret:.2f}")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
