"""Which attack a RAT run's own r̂ prefers: the adversary network's Δ alone, or Δ refined towards π_θ.

    python benchmarks/refine_choice.py RUN [RUN ...] [--episodes 10]

For each finished RAT run that refines Δ at attack time (``refine_steps`` > 0), both attacks are played on
the same episodes (those a run scores its snapshots on: ``seeds.SELECTION``) and scored by the run's final
r̂, the attacker's own yardstick; no true reward is used. Beside them, the attack success of each on the
run's final 30 episodes, from its ``report.json``, shows whether r̂ chose the better one. Results are
recorded in ``benchmarks/strength.md``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from rat import seeds
from rat.attacks import ThreatModel
from rat.attacks.rat import load_rat_attack, policy_learned_return
from rat.attacks.threat import AttackedObservation
from rat.errors import RatError
from rat.experiments.runner import attack_setup
from rat.preferences.offline import run_reward
from rat.reports import AttackReport
from rat.runs import read_run_config
from rat.victims.base import VictimPolicy


def learned_returns(run: Path, episodes: int) -> dict:
    """r̂'s mean return for the network's Δ and for the refined attack, with the report's success of each."""
    config, report = read_run_config(run), AttackReport.read(run)
    if "rat" not in config or not config["rat"].get("refine_steps"):
        raise RatError(f"'{run}' is no RAT run that refines Δ (refine_steps > 0), so its report has no refined "
                       "success to compare; give one that does")
    threat = ThreatModel(report.epsilon, report.norm)
    setup = attack_setup(config["victim"], report.target, threat, report.seed, progress=False)
    env = setup.make_env(report.seed + seeds.SELECTION_ENV)
    ensemble, _ = run_reward(run, env.observation_space.shape[0], env.action_space.shape[0])
    scores = {}
    for name, steps in (("network", 0), ("refined", None)):  # None: as the run refines
        attacked = AttackedObservation(env, load_rat_attack(run, setup.victim, refine_steps=steps), threat)
        scores[name] = policy_learned_return(VictimPolicy(setup.victim), attacked, ensemble, episodes, seeds.SELECTION)
    return {"run": run.name, "r_hat_network": scores["network"], "r_hat_refined": scores["refined"],
            "success_network": report.details.get("network_attack_success_rate"),
            "success_refined": report.attack_success_rate}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+", help="finished RAT runs that refine Δ")
    parser.add_argument("--episodes", type=int, default=10, help="episodes each attack is scored on")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print("| run | r̂ return: network's Δ | refined | r̂ prefers | success (30 ep.): network's Δ | refined |")
    print("| --- | ---: | ---: | --- | ---: | ---: |")
    for run in args.runs:
        try:
            row = learned_returns(run, args.episodes)
        except RatError as exc:
            parser.error(str(exc))
        prefers = "refined" if row["r_hat_refined"] >= row["r_hat_network"] else "network"
        print(f"| {row['run']} | {row['r_hat_network']:.1f} | {row['r_hat_refined']:.1f} | {prefers} | "
              f"{row['success_network']:.1%} | {row['success_refined']:.1%} |", flush=True)


if __name__ == "__main__":
    main()
