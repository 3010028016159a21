"""Does the unattacked walker pass a walker target's success test on its own? The longest runs of each
test's condition over clean episodes of a Walker2d victim, and its speed once under way.

    python benchmarks/clean_gait.py --victim zoo:dt/walker2d-v5 --episodes 30

A target's success needs its condition held for a number of steps in a row (``rat.envs.locomotion``);
the hold must exceed what the clean gait reaches, or the target is vacuous. Recorded in the README's
locomotion section and ``benchmarks/dt.md``.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from rat.envs import make_task
from rat.envs.locomotion import _leg_raised, _one_foot
from rat.errors import RatError
from rat.victims import load_victim
from rat.victims.base import numpy_policy


def longest(flags: list[bool]) -> int:
    best = run = 0
    for flag in flags:
        run = run + 1 if flag else 0
        best = max(best, run)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--victim", default="zoo:dt/walker2d-v5")
    parser.add_argument("--episodes", type=int, default=30)
    args = parser.parse_args()
    torch.set_num_threads(1)
    try:
        victim = load_victim(args.victim)
    except RatError as exc:
        parser.error(str(exc))
    env, policy = make_task("Walker2d-v5", seed=0), numpy_policy(victim)
    rows = []
    for episode in range(args.episodes):
        obs, _ = env.reset(seed=episode)
        if hasattr(policy, "reset"):
            policy.reset()
        infos = []
        for _ in range(1000):
            obs, reward, terminated, truncated, info = env.step(policy(obs))
            if hasattr(policy, "observe"):
                policy.observe(reward)
            infos.append(info)
            if terminated or truncated:
                break
        feet = [info["torso_z"] > 0.9 and ((info["foot_z"] > 0.15 and info["foot_left_z"] < 0.1)
                                           or (info["foot_left_z"] > 0.15 and info["foot_z"] < 0.1)) for info in infos]
        rows.append((longest(feet), longest([_one_foot(i) for i in infos]), longest([_leg_raised(i) for i in infos]),
                     min((abs(i["x_velocity"]) for i in infos[100:]), default=float("nan"))))
    a = np.array(rows)
    print(f"{args.episodes} clean episodes of {args.victim}; longest runs of consecutive steps (max / median):")
    print(f"  one foot up, the other down, any speed: {a[:, 0].max():.0f} / {np.median(a[:, 0]):.0f}")
    print(f"  walker-one-foot's condition (and under 0.5 m/s): {a[:, 1].max():.0f} / {np.median(a[:, 1]):.0f}")
    print(f"  walker-leg-raised's condition: {a[:, 2].max():.0f} / {np.median(a[:, 2]):.0f}")
    print(f"  slowest speed after step 100: {np.nanmin(a[:, 3]):.2f} m/s")


if __name__ == "__main__":
    main()
