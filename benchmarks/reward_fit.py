"""How well r̂ can fit a run's own preference labels: a reward ensemble trained from scratch on 8/9 of a
label store, scored on the other 1/9 — preference accuracy, and r̂'s correlation with the true target
reward per step of the held-out segments (the store keeps each step's true reward beside the label).

It trains with the ensemble's own rounds (``RewardEnsemble.train_round``, ``--every`` updates a member a
round, as a RAT run's capped rounds do, on all the training labels each time), so a setting of
``RewardModelConfig`` measured here is the one a run would use:

    python benchmarks/reward_fit.py runs/RUN --updates 4000                      # PEBBLE's raw inputs
    python benchmarks/reward_fit.py runs/RUN --updates 4000 --normalize-inputs   # standardised inputs

Results are recorded in ``docs/notes/strength-log.md``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from rat.preferences.reward_model import RewardEnsemble, RewardModelConfig
from rat.preferences.store import LabelStore


def scores(ensemble: RewardEnsemble, pairs, y: np.ndarray, big: float) -> dict[str, float]:
    """Preference accuracy (equal labels count as right), the same on pairs whose true returns differ by at
    least ``big``, and the per-step correlation of r̂ with the true reward."""
    r0, r1 = ensemble.r_hat(pairs.obs0, pairs.act0), ensemble.r_hat(pairs.obs1, pairs.act1)
    right = ((r1.sum(-1) > r0.sum(-1)) == (y == 1)) | (y == 0.5)
    gap = np.abs(pairs.reward1.sum(-1) - pairs.reward0.sum(-1))
    steps, truth = np.concatenate([r0, r1]).ravel(), np.concatenate([pairs.reward0, pairs.reward1]).ravel()
    known = np.isfinite(truth)
    return {"accuracy": float(right.mean()), "accuracy_big": float(right[gap >= big].mean()),
            "step_corr": float(np.corrcoef(steps[known], truth[known])[0, 1])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a run directory (its labels.sqlite) or a label store")
    parser.add_argument("--updates", type=int, default=4000, help="gradient steps a member in all")
    parser.add_argument("--every", type=int, default=500, help="gradient steps a member a round, scored after each")
    parser.add_argument("--members", type=int, default=1)
    parser.add_argument("--hidden", type=int, default=256)
    parser.add_argument("--layers", type=int, default=3)
    parser.add_argument("--normalize-inputs", action="store_true")
    parser.add_argument("--lr", type=float, default=RewardModelConfig.lr, help="Adam's learning rate")
    parser.add_argument("--big", type=float, default=0.5, help="a true-return gap counted as clear")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.lr <= 0:
        parser.error(f"--lr must be positive, got {args.lr}")
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    store = args.run / "labels.sqlite" if args.run.is_dir() else args.run
    with LabelStore(store, read_only=True) as labels:
        data = labels.read()
    order = rng.permutation(len(data))
    held, train = order[: len(order) // 9], order[len(order) // 9:]
    def part(index):
        return type(data.pairs)(*(getattr(data.pairs, f)[index] for f in
                                               ("obs0", "act0", "reward0", "obs1", "act1", "reward1")))
    tr, te = part(train), part(held)
    config = RewardModelConfig(members=args.members, hidden=args.hidden, layers=args.layers, max_epochs=10 ** 6,
                               max_updates=args.every, normalize_inputs=args.normalize_inputs, lr=args.lr)
    ensemble = RewardEnsemble(tr.obs0.shape[-1], tr.act0.shape[-1], config)
    print(f"{store}: {len(train)} training labels, {len(held)} held out; {args.members} member(s) "
          f"{args.layers}×{args.hidden}, lr {args.lr:g}, inputs {'standardised' if args.normalize_inputs else 'raw'}")
    print("| updates | training accuracy | held-out accuracy | held-out, |ΔR| ≥ "
          f"{args.big} | r̂ vs true reward per step | seconds |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: |")
    start, done = time.time(), 0
    while done < args.updates:  # a round may stop short of --every at the ensemble's stop_accuracy: count what ran
        metrics = ensemble.train_round(tr.obs0, tr.act0, tr.obs1, tr.act1, data.y[train], rng)
        done += int(metrics["reward_updates"])
        s = scores(ensemble, te, data.y[held], args.big)
        print(f"| {done} | {metrics['reward_train_accuracy']:.3f} | {s['accuracy']:.3f} | {s['accuracy_big']:.3f} | "
              f"{s['step_corr']:.2f} | {time.time() - start:.0f} |", flush=True)


if __name__ == "__main__":
    main()
