"""A RAT run's attack refined by each refinement loss in turn, on the episodes of the run's own final evaluation.

The episodes are the report's (reset with the final evaluation's seeds, in the environment the run evaluated
in), so the loss the run was trained with reproduces its report, and each other loss is compared with it
episode by episode (exact McNemar test on the episodes where the two disagree):

    python benchmarks/refine_losses.py RUN_DIR --losses l2,q --episodes 30

Results are recorded in ``docs/notes/strength-log.md``.
"""

from __future__ import annotations

import argparse
import json
import time
from math import comb
from pathlib import Path

import numpy as np
import torch

from rat import seeds
from rat.attacks.evaluation import evaluate_attack
from rat.attacks.saved import load_rat_attack, load_saved
from rat.attacks.threat import ThreatModel
from rat.envs import get_target, make_task
from rat.errors import RatError
from rat.victims import load_victim


def mcnemar(first: list[bool], second: list[bool]) -> float:
    """Two-sided exact McNemar p-value for paired successes."""
    only_first = sum(a and not b for a, b in zip(first, second))
    only_second = sum(b and not a for a, b in zip(first, second))
    n = only_first + only_second
    return min(1.0, 2 * sum(comb(n, k) for k in range(min(only_first, only_second) + 1)) / 2**n) if n else 1.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a RAT run directory, or one of its saved adversaries")
    parser.add_argument("--losses", default="l2,q", help="comma-separated refinement losses; the first is the baseline")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--steps", type=int, default=None, help="refinement steps [the run's refine_steps]")
    parser.add_argument("--switch-gap", type=float, default=None,
                        help="l2-or-q's threshold, for that loss alone [the run's refine_switch_gap]")
    args = parser.parse_args()
    torch.set_num_threads(1)
    try:
        _, _, meta = load_saved(args.run)
        victim, cfg = load_victim(meta["victim"]), meta["rat"]
        attacks = {}
        for loss in args.losses.split(","):
            gaps: list[float] = []  # the gap each loss leaves to π_θ's actions, per observation
            attacks[loss] = (load_rat_attack(args.run, victim, args.steps, gaps, loss,
                                                       args.switch_gap if loss == "l2-or-q" else None), gaps)
    except RatError as exc:
        parser.error(str(exc))
    threat, target = ThreatModel(cfg["epsilon"], cfg["norm"]), get_target(meta["target"])
    make_env = lambda: make_task(meta["task"], seed=cfg["seed"] + seeds.EVAL_ENV)  # noqa: E731 (the run's own)
    results = {}
    for loss, (attack, gaps) in attacks.items():
        start = time.time()
        res = evaluate_attack(victim, attack, make_env(), target, threat, args.episodes, seeds.FINAL, make_env=make_env)
        results[loss] = res.result.successes
        baseline = next(iter(results.values()))
        print(json.dumps({"run": str(args.run), "loss": loss, "success": res.result.success_rate,
                          "episodes": args.episodes, "gap": round(float(np.mean(gaps)), 3),
                          "max_perturbation": res.max_perturbation, "mcnemar_p_vs_first": mcnemar(baseline, results[loss]),
                          "successes": [int(x) for x in res.result.successes],
                          "minutes": round((time.time() - start) / 60, 1)}), flush=True)


if __name__ == "__main__":
    main()
