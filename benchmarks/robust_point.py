"""Robust training on the tests' point environment, every method in about a minute a run: table 3 in miniature.

Per seed, one fixed attack: a RAT attack trained against the undefended point controller (the point SAC victim)
and frozen. Each method's robust agent is fine-tuned from that controller (the recipe of
``tests/test_robust.py::test_a_rat_atla_agent_beats_the_undefended_victim_under_a_fixed_attack``; it never sees the
fixed attack, only its own adversary), and it and the controller are attacked by the fixed attack. Each line
printed is one seed and method: the task return ± std and the target's success over 50 attacked episodes, for the
undefended controller and for the robust agent.

    python benchmarks/robust_point.py --seeds 0,1,2                                  # RAT-ATLA, the cpu preset's anchor
    python benchmarks/robust_point.py --seeds 0,1,2 --set anchor=0                   # without the anchor
    python benchmarks/robust_point.py --seeds 0,1,2 --methods rat-atla,rat-wocar,atla,pa-atla
    python benchmarks/robust_point.py --seeds 0,1,2 --methods rat-wocar --set wocar_critic=worst-case

Results: benchmarks/table3.md#the-point-environment-table-3-in-miniature.
"""

from __future__ import annotations

import argparse
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
from rat.attacks.base import AttackSetup  # noqa: E402
from rat.attacks.evaluation import evaluate_attack  # noqa: E402
from rat.attacks.rat import train_rat  # noqa: E402
from rat.attacks.rl import PPOConfig  # noqa: E402
from rat.attacks.saved import adversary_function, load_adversary  # noqa: E402
from rat.attacks.threat import ThreatModel  # noqa: E402
from rat.configs import parse_assignment, with_values  # noqa: E402
from rat.robust import RobustConfig, prepare_robust  # noqa: E402
from rat.robust.trainer import RobustTrainer  # noqa: E402

EPS = ThreatModel(0.1)
EPISODES = 50  #: attacked episodes of each agent
ATTACK_STEPS = 2000  #: the fixed attack's training steps (as long as the robust agents' phase 0)
POINT_RECIPE = dict(agent_steps=4000, phase_steps=400, adversary_phase_steps=400, first_adversary_steps=2000,
                    critic_warmup=2000, warmup_updates=4, warmup_noise=0.0, finetune_temperature=0.01,
                    eval_every=10**6, eval_episodes=5, final_eval_episodes=10, checkpoint_every=10**6,
                    sac=SACConfig(hidden=64, layers=2, batch_size=128, lr=3e-4))
PPO = PPOConfig(learning_rate=1e-3, batch_size=100, n_steps=200, n_epochs=2, hidden=32, layers=1)  #: ATLA, PA-ATLA


def fixed_attack(seed: int, out: Path):
    """RAT trained against the undefended controller, frozen: ``obs -> Δ``."""
    setup = AttackSetup(point_sac_victim(), BESIDE, PointGoal, EPS, seed=seed, progress=False)
    train_rat(small_config(ATTACK_STEPS, seed=seed), setup, out)
    adversary, _ = load_adversary(out / "adversary")
    return adversary_function(adversary.eval())


def robust_agent(method: str, seed: int, overrides: dict, out: Path) -> RobustTrainer:
    """The finished trainer of ``method``'s robust agent from the point controller."""
    cfg = with_values(RobustConfig(method=method, seed=seed, **POINT_RECIPE), overrides)
    adversary = small_config(6000) if cfg.adversary_method == "rat" else PPO if cfg.adversary_method else None
    _, trainer, _ = prepare_robust(cfg, point_sac_victim(), BESIDE, PointGoal, EPS, out, adversary,
                                   describe={"task": "point"}, progress=False)
    while not trainer.finished:
        trainer.advance()
    return trainer


def attacked(agent, attack) -> dict:
    r = evaluate_attack(agent, attack, PointGoal(7), BESIDE, EPS, EPISODES, seed=2 * 10**7).result
    return {"return": round(r.mean_return, 3), "std": round(r.std_return, 3), "target": r.success_rate}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--methods", default="rat-atla")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="a RobustConfig field")
    args = parser.parse_args()
    overrides = dict(parse_assignment(RobustConfig, a) for a in args.set)
    torch.set_num_threads(1)
    for seed in (int(s) for s in args.seeds.split(",")):
        with tempfile.TemporaryDirectory() as tmp:  # fresh run directories: nothing of an earlier run is reused
            attack = fixed_attack(seed, Path(tmp) / "attack")
            undefended = attacked(point_sac_victim(), attack)
            for method in args.methods.split(","):
                t0 = time.perf_counter()
                trainer = robust_agent(method, seed, overrides, Path(tmp) / method)
                row = {"seed": seed, "method": method, **overrides, "episodes": EPISODES, "undefended": undefended,
                       "robust": attacked(trainer.current_agent(), attack), **trainer.counters,
                       "minutes": round((time.perf_counter() - t0) / 60, 2)}
                print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
