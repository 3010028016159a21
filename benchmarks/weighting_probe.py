"""What the weighting network learns, with and without normalised weights, on a finished RAT run's data.

    python benchmarks/weighting_probe.py RUN --victim zoo:faucet-close-v3 --target reach --budget 9000

From the run's last checkpoint (its replay buffer, adversary, π_θ and r̂), a fresh weighting network is
trained for ``--phases`` phases of RAT's own schedule — 10 adversary updates, then one weighting update —
once in the paper's form (mean_s h(s)·KL_s) and once normalised (Σ h·KL / Σ h), each from the same
state. Printed per form: the weights' mean and their spread over 4,096 stored states, every 100
phases. The paper's form can lower the outer loss by raising every weight at once; the question is
whether either form re-weights states, i.e. whether the spread grows.
"""

from __future__ import annotations

import argparse
import copy
import tempfile
from pathlib import Path

import torch

from rat.attacks.losses import WeightingNetwork
from rat.attacks.rat import RATTrainer
from rat.checkpoint import load_checkpoint
from rat.experiments.presets import rat_config
from rat.experiments.runner import attack_setup
from rat.preferences.store import LabelStore


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--victim", default="zoo:faucet-close-v3")
    parser.add_argument("--target", default="reach")
    parser.add_argument("--budget", type=int, default=9000)
    parser.add_argument("--phases", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)

    state, meta = load_checkpoint(args.run / "checkpoint")
    print(f"{args.run}, checkpoint at step {meta['step']}; {args.phases} phases per form\n")
    print("| form | phase | weight mean | weight std over states | min | max |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for norm in ("none",):  # the normalised form ("batch") measured beside it in docs/notes/strength-log.md lost and was removed
        cfg = rat_config("cpu", budget=args.budget, target=args.target, seed=args.seed)
        setup = attack_setup(args.victim, args.target, cfg.threat, progress=False)
        tmp = Path(tempfile.mkdtemp())
        trainer = RATTrainer(cfg, setup, setup.make_env(0), LabelStore(tmp / "labels.sqlite"), "probe", tmp / "s")
        trainer.load_state_dict(copy.deepcopy(state), meta)
        torch.manual_seed(args.seed)
        trainer.weighting = WeightingNetwork(trainer.adversary.obs_dim)  # fresh: h ≈ 1 everywhere
        trainer.weighting_opt = torch.optim.Adam(trainer.weighting.parameters(), lr=cfg.weighting_lr)
        probe, _ = trainer.sample_states()
        probe = torch.cat([probe] + [trainer.sample_states()[0] for _ in range(4096 // len(probe) - 1)])
        for phase in range(args.phases + 1):
            if phase % 100 == 0:
                with torch.no_grad():
                    w = trainer.weighting(probe)
                print(f"| {norm} | {phase} | {w.mean():.3f} | {w.std():.4f} | {w.min():.3f} | {w.max():.3f} |",
                      flush=True)
            for _ in range(cfg.adversary_updates):
                trainer.adversary_step()
            trainer.weighting_step()


if __name__ == "__main__":
    main()
