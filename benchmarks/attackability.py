"""How far can a per-step attacker that *knows* where to go push a zoo victim inside the ε-ball?

A white-box reference for the learned attacks: at every step, PA-AD's actor
(:func:`rat.attacks.gradient.directed_perturbation`, PGD) moves the victim's action along a
scripted direction: towards the manipulation goal (``reach``), or along the action of the
target task's Meta-World scripted expert (``opposite``: e.g. faucet-open-v3's expert against the
faucet-close victim). No learning is involved, so the numbers say what the victim's sensitivity
to ε allows a greedy attacker, not what an attack method achieves.

    python benchmarks/attackability.py --victim faucet-close-v3 --targets opposite --epsilons 0.1,0.2 --episodes 5
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from rat.attacks.gradient import directed_perturbation
from rat.attacks.threat import ThreatModel
from rat.envs import get_target, make_task
from rat.envs.targets import REACH_GOAL
from rat.victims import load_victim
from rat.victims.experts import expert_for


def direction(target: str, obs: np.ndarray, expert) -> torch.Tensor:
    if target == "reach":
        d = torch.zeros(1, 4)
        d[0, :3] = torch.as_tensor(REACH_GOAL - obs[:3])
        return d
    return torch.as_tensor(expert.get_action(obs), dtype=torch.float32).unsqueeze(0)  # the target task's expert


def run(victim_task: str, target_name: str, epsilon: float, episodes: int, steps: int) -> dict:
    victim, target = load_victim(f"zoo:{victim_task}"), get_target(target_name)
    env = make_task(target.env_task(victim_task), seed=0)
    expert = expert_for(target.env_task(victim_task))
    rng, threat = np.random.default_rng(0), ThreatModel(epsilon, "linf")
    successes, closest = [], []
    for episode in range(episodes):
        obs, _ = env.reset(seed=1000 + episode)
        success, best, test = False, np.inf, target.episode_success()
        for _ in range(500):
            s = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
            delta = directed_perturbation(victim, s, direction(target_name, obs, expert), threat, steps=steps,
                                          generator=rng)
            with torch.no_grad():
                action = victim.act(threat.perturb(s, delta)).squeeze(0).numpy()
            obs, _, terminated, truncated, info = env.step(action)
            success |= test(info)
            best = min(best, float(np.linalg.norm(info["tcp_pos"] - REACH_GOAL)))
            if terminated or truncated:
                break
        successes.append(success)
        closest.append(best)
    env.close()
    return {"success": float(np.mean(successes)), "closest_to_reach_goal": float(np.mean(closest))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--victim", default="drawer-open-v3")
    parser.add_argument("--targets", default="reach,opposite")
    parser.add_argument("--epsilons", default="0.1,0.15,0.2")
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--pgd-steps", type=int, default=10)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print("| target | ε (ℓ∞) | greedy white-box success | gripper's closest approach to the reach goal (m) |")
    print("| --- | ---: | ---: | ---: |")
    for target in args.targets.split(","):
        for epsilon in (float(e) for e in args.epsilons.split(",")):
            r = run(args.victim, target, epsilon, args.episodes, args.pgd_steps)
            print(f"| {target} | {epsilon:g} | {100 * r['success']:.0f}% ({args.episodes} ep.) | "
                  f"{r['closest_to_reach_goal']:.3f} |", flush=True)


if __name__ == "__main__":
    main()
