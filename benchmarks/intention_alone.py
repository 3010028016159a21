"""How often the intention policy a RAT run saved beside its adversary does the target behaviour alone.

Refinement (``refine_steps``) brings the victim towards this π_θ's actions, so its own success is the
yardstick for the refined attack. Deterministic actions (tanh of the mean), on the target's task:

    python benchmarks/intention_alone.py RUN_DIR --episodes 10
    python benchmarks/intention_alone.py RUN_DIR/adversary-last --episodes 10

Results are recorded in ``docs/notes/strength-log.md``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from rat.attacks.saved import load_saved
from rat.envs import make_task
from rat.envs.targets import get_target
from rat.errors import RatError
from rat.eval import evaluate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a RAT run directory, or one of its saved adversaries")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=1000, help="episode i is reset with seed + i")
    args = parser.parse_args()
    torch.set_num_threads(1)
    try:
        _, imitated, meta = load_saved(args.run)
    except RatError as exc:
        parser.error(str(exc))
    if imitated is None:
        parser.error(f"'{args.run}' holds no intention policy (saved by an older version); run its `rat attack train` "
                     "command again to rewrite it")
    target = get_target(meta["target"])

    @torch.no_grad()
    def act(obs: np.ndarray) -> np.ndarray:
        return imitated.actor(torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)).squeeze(0).numpy()

    result = evaluate(act, make_task(target.env_task(meta["task"]), seed=1), args.episodes, args.seed, target=target)
    print(f"π_θ alone at '{target.name}': {result.success_rate:.1%} over {args.episodes} episodes")


if __name__ == "__main__":
    main()
