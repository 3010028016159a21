"""Robust-training settings on the tests' point environment, in about a minute a run.

A RAT-ATLA agent is fine-tuned from the point controller (the recipe of
``tests/test_robust.py::test_a_rat_atla_agent_beats_the_undefended_victim_under_a_fixed_attack``), and both it and
the undefended controller are attacked by one fixed adversary: phase 0's RAT adversary, trained against the
undefended controller and frozen there. Each line printed is one seed: the task return ± std and the target's
success over 50 attacked episodes, for each of the two agents.

    python benchmarks/robust_point.py --seeds 0,1,2                 # the cpu preset's anchor (λ = 0.4)
    python benchmarks/robust_point.py --seeds 0,1,2 --set anchor=0  # without it

Results: benchmarks/table3.md#the-anchor.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))  # the tests' point environment

from point_env import BESIDE, PointGoal, point_sac_victim  # noqa: E402
from test_rat_training import small_config  # noqa: E402

from rat.agents.sac import SACConfig  # noqa: E402
from rat.attacks.evaluation import evaluate_attack  # noqa: E402
from rat.attacks.threat import ThreatModel  # noqa: E402
from rat.configs import parse_assignment, with_values  # noqa: E402
from rat.robust import RobustConfig, prepare_robust  # noqa: E402

EPS = ThreatModel(0.1)
EPISODES = 50  #: attacked episodes of each agent
POINT_RECIPE = dict(method="rat-atla", agent_steps=4000, phase_steps=400, adversary_phase_steps=400,
                    first_adversary_steps=2000, critic_warmup=2000, warmup_updates=4, warmup_noise=0.0,
                    finetune_temperature=0.01, eval_every=10**6, eval_episodes=5, final_eval_episodes=10,
                    checkpoint_every=10**6, sac=SACConfig(hidden=64, layers=2, batch_size=128, lr=3e-4))


def one_seed(seed: int, overrides: dict, out: Path) -> dict:
    t0 = time.perf_counter()
    cfg = with_values(RobustConfig(**POINT_RECIPE | {"seed": seed}), overrides)
    victim = point_sac_victim()
    _, trainer, _ = prepare_robust(cfg, victim, BESIDE, PointGoal, EPS, out, small_config(6000),
                                   describe={"task": "point"}, progress=False)
    fixed = None
    while not trainer.finished:
        trainer.advance()
        if fixed is None and trainer.phase == "agent":  # phase 0 just ended: its adversary, frozen
            fixed = copy.deepcopy(trainer.adversary.trainer.adversary).eval()

    @torch.no_grad()
    def attack(obs):
        return fixed(torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)).squeeze(0).double().numpy()

    row = {"seed": seed, **overrides, "episodes": EPISODES}
    for name, agent in (("undefended", victim), ("robust", trainer.current_agent())):
        r = evaluate_attack(agent, attack, PointGoal(7), BESIDE, EPS, EPISODES, seed=2 * 10**7).result
        row[name] = {"return": round(r.mean_return, 3), "std": round(r.std_return, 3), "target": r.success_rate}
    return row | {**trainer.counters, "minutes": round((time.perf_counter() - t0) / 60, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="a RobustConfig field")
    args = parser.parse_args()
    overrides = dict(parse_assignment(RobustConfig, a) for a in args.set)
    torch.set_num_threads(1)
    for seed in (int(s) for s in args.seeds.split(",")):
        with tempfile.TemporaryDirectory() as out:  # a fresh run directory: nothing of an earlier run is reused
            print(json.dumps(one_seed(seed, overrides, Path(out) / "run")), flush=True)


if __name__ == "__main__":
    main()
