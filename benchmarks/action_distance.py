"""How far has a fine-tuned victim moved from the one it started from? The mean absolute difference of their
deterministic actions, on the observations of the fine-tuned victim's own clean episodes.

    python benchmarks/action_distance.py zoo:door-lock-v3@sac-ft zoo:door-lock-v3@bc --episodes 3

Recorded in ``benchmarks/zoo.md`` (the SAC-fine-tuned clones): actions lie in [-1, 1], so 0 means the same
policy and values near 1 a different one.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from rat.envs import make_task
from rat.errors import RatError
from rat.victims import load_victim


def action_distance(tuned: str, start: str, episodes: int, seed: int = 5) -> tuple[float, float]:
    """Mean and 90th percentile of |a_tuned - a_start| (averaged over action dimensions) along ``tuned``'s
    episodes."""
    a, b = load_victim(tuned), load_victim(start)
    task = a.meta.get("task")
    if task is None or task != b.meta.get("task"):
        raise RatError(f"{tuned} and {start} must be victims of the same task")
    env, gaps = make_task(task, seed=seed), []
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        done = False
        while not done:
            x = torch.as_tensor(obs[None], dtype=torch.float32)
            with torch.no_grad():
                mine, theirs = a.act(x).numpy(), b.act(x).numpy()
            gaps.append(float(np.abs(mine - theirs).mean()))
            obs, _, terminated, truncated, _ = env.step(mine[0])
            done = terminated or truncated
    return float(np.mean(gaps)), float(np.percentile(gaps, 90))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tuned")
    parser.add_argument("start")
    parser.add_argument("--episodes", type=int, default=3)
    args = parser.parse_args()
    mean, p90 = action_distance(args.tuned, args.start, args.episodes)
    print(f"{args.tuned} vs {args.start}: mean |Δa| {mean:.4f}, 90th percentile {p90:.4f} "
          f"({args.episodes} episodes of {args.tuned})")


if __name__ == "__main__":
    main()
