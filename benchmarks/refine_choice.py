"""Which attack a RAT run's own r̂ prefers: the adversary network's Δ alone, or Δ refined towards π_θ.

    python benchmarks/refine_choice.py RUN [RUN ...] [--episodes 10] [--pairs 0]

For each finished RAT run that refines Δ at attack time (``refine_steps`` > 0), both attacks are played on
the same episodes (those a run scores its snapshots on: ``seeds.SELECTION``) and scored by the run's final
r̂, the attacker's own yardstick; no true reward is used. Beside them, the attack success of each on the
run's final 30 episodes, from its ``report.json``, shows whether r̂ chose the better one.

``--pairs K`` then shows the first K of those same episodes (each attack plays every episode once) and prints,
per episode, what the run's scripted teacher sees and says: each attack's true target return, the steps at which the
target's success test holds, and the teacher's label for the pair (its own settings; 1 prefers the refined
attack). Results are recorded in ``docs/notes/strength-log.md``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from rat import seeds
from rat.attacks import ThreatModel
from rat.attacks.saved import load_rat_attack
from rat.attacks.threat import AttackedObservation
from rat.envs.targets import TargetBehaviour
from rat.errors import RatError
from rat.experiments.runner import attack_setup
from rat.preferences.offline import run_reward
from rat.preferences.segments import SegmentPairs
from rat.preferences.teacher import ScriptedTeacher, TeacherConfig
from rat.reports import AttackReport
from rat.runs import read_run_config
from rat.victims.base import VictimPolicy


def true_episode(victim, attacked: AttackedObservation, target: TargetBehaviour, seed: int) -> tuple[np.ndarray, ...]:
    """One attacked episode: true observations, actions, the target's reward and its success test at every step."""
    policy = VictimPolicy(victim)
    seen, info = attacked.reset(seed=seed)
    policy.reset()
    test, steps, done = target.episode_success(), [], False
    while not done:
        true, action = info["true_obs"], policy(seen)
        seen, reward, terminated, truncated, info = attacked.step(action)
        policy.observe(reward)
        steps.append((true, action, target.reward(true, action, info["true_obs"], info), test(info)))
        done = terminated or truncated
    return tuple(np.asarray(column) for column in zip(*steps))


def compare(run: Path, episodes: int, pairs: int = 0) -> tuple[dict, list[dict]]:
    """Both attacks played once on the same episodes (``max(episodes, pairs)`` of them): r̂'s mean return of each over
    the first ``episodes``, with the report's success of each; and per episode of the first ``pairs``, each attack's
    true return and steps at success and the run's teacher's label for the two (1: the refined one preferred)."""
    config, report = read_run_config(run), AttackReport.read(run)
    if "rat" not in config or not config["rat"].get("refine_steps"):
        raise RatError(f"'{run}' is no RAT run that refines Δ (refine_steps > 0), so its report has no refined "
                       "success to compare; give one that does")
    threat = ThreatModel(report.epsilon, report.norm)
    setup = attack_setup(config["victim"], report.target, threat, report.seed, progress=False)
    env = setup.make_env(report.seed + seeds.SELECTION_ENV)
    ensemble, _ = run_reward(run, env.observation_space.shape[0], env.action_space.shape[0])
    played = {}
    for name, steps in (("network", 0), ("refined", None)):  # None: as the run refines
        attacked = AttackedObservation(env, load_rat_attack(run, setup.victim, refine_steps=steps), threat)
        played[name] = [true_episode(setup.victim, attacked, setup.target, seeds.SELECTION + i)
                        for i in range(max(episodes, pairs))]
    # r̂ scores the true state, as a run scoring its snapshots does (rat.attacks.rat.policy_learned_return)
    r_hat = {name: float(np.mean([ensemble.r_hat(obs.astype(np.float32), act).sum() for obs, act, *_ in eps[:episodes]]))
             for name, eps in played.items()}
    summary = {"run": run.name, "r_hat_network": r_hat["network"], "r_hat_refined": r_hat["refined"],
               "success_network": report.details.get("network_attack_success_rate"),
               "success_refined": report.attack_success_rate}
    teacher = ScriptedTeacher(TeacherConfig(**config["rat"]["pebble"]["teacher"]))
    rows = []
    for i, ((o0, a0, r0, ok0), (o1, a1, r1, ok1)) in enumerate(zip(played["network"][:pairs], played["refined"][:pairs])):
        length = min(len(r0), len(r1))  # Meta-World's episodes all run to the time limit
        pair = SegmentPairs(o0[None, :length], a0[None, :length], r0[None, :length], o1[None, :length],
                            a1[None, :length], r1[None, :length])
        label = teacher.label(pair, np.random.default_rng(i)).y
        rows.append({"episode": i, "return_network": r0.sum(), "success_steps_network": int(ok0.sum()),
                     "return_refined": r1.sum(), "success_steps_refined": int(ok1.sum()),
                     "teacher": float(label[0]) if len(label) else None})
    return summary, rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+", help="finished RAT runs that refine Δ")
    parser.add_argument("--episodes", type=int, default=10, help="episodes each attack is scored on")
    parser.add_argument("--pairs", type=int, default=0, help="episodes to replay for the run's teacher (0: none)")
    args = parser.parse_args()
    if args.episodes < 1 or args.pairs < 0:
        parser.error(f"--episodes must be at least 1 and --pairs at least 0, got {args.episodes} and {args.pairs}")
    torch.set_num_threads(1)
    print("| run | r̂ return: network's Δ | refined | r̂ prefers | success (30 ep.): network's Δ | refined |")
    print("| --- | ---: | ---: | --- | ---: | ---: |")
    compared = []
    for run in args.runs:
        try:
            row, pairs = compare(run, args.episodes, args.pairs)
        except RatError as exc:
            parser.error(str(exc))
        compared.append((run, pairs))
        prefers = "refined" if row["r_hat_refined"] >= row["r_hat_network"] else "network"
        print(f"| {row['run']} | {row['r_hat_network']:.1f} | {row['r_hat_refined']:.1f} | {prefers} | "
              f"{row['success_network']:.1%} | {row['success_refined']:.1%} |", flush=True)
    for run, pairs in compared if args.pairs else ():
        print(f"\n{run.name}: the same episodes, as the run's teacher sees them\n")
        print("| episode | true return: network's Δ | steps at success | refined | steps at success | teacher's label |")
        print("| ---: | ---: | ---: | ---: | ---: | ---: |")
        for row in pairs:
            print(f"| {row['episode']} | {row['return_network']:.0f} | {row['success_steps_network']} | "
                  f"{row['return_refined']:.0f} | {row['success_steps_refined']} | {row['teacher']} |", flush=True)

if __name__ == "__main__":
    main()
