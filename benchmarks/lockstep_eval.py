"""A refined RAT attack evaluated one episode at a time and in lockstep: the time each takes, and the numbers.

Refinement runs ``refine_steps`` Adam steps through the victim at every observation; in lockstep the
running episodes' observations are refined together, one pass of the networks per step for all of them.

    python benchmarks/lockstep_eval.py RUN_DIR --episodes 6

Prints, per mode, the minutes, each episode's success and the mean return. Results are recorded in
``benchmarks/rat_profile.md``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from rat.attacks.base import saved_attack_meta
from rat.attacks.evaluation import evaluate_attack
from rat.attacks.saved import load_rat_attack
from rat.attacks.threat import ThreatModel
from rat.envs import make_task
from rat.envs.targets import get_target
from rat.victims import load_victim


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a RAT run directory that refines (refine_steps > 0)")
    parser.add_argument("--episodes", type=int, default=6)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    meta = saved_attack_meta(args.run)
    victim, target = load_victim(meta["victim"]), get_target(meta["target"])
    threat = ThreatModel(meta["rat"]["epsilon"], meta["rat"]["norm"])
    for mode, width in (("one at a time", 1), ("lockstep", args.episodes)):
        gaps: list[float] = []
        attack = load_rat_attack(args.run, victim, gaps=gaps)
        start = time.perf_counter()
        result = evaluate_attack(victim, attack, make_task(meta["task"], seed=args.seed), target, threat,
                                 args.episodes, args.seed, make_env=lambda: make_task(meta["task"], seed=args.seed),
                                 lockstep=width).result
        minutes = (time.perf_counter() - start) / 60
        print(f"{mode}: {minutes:.2f} min | successes {[int(s) for s in result.successes]} | "
              f"mean return {result.mean_return:.3f} | gap left {sum(gaps) / len(gaps):.4f}", flush=True)


if __name__ == "__main__":
    main()
