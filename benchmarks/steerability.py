"""How far can a greedy white-box attacker steer a victim inside the ε-ball? A reference for the learned attacks.

At every step the attacker knows where the victim should go and searches the ball for the
observation that turns the victim's action most that way: 16 random starts × 30 steps of
projected gradient ascent on the goal-ward component of the victim's action (as seen from the
gripper, for Meta-World), keeping the best start. Nothing is learnt, so the numbers say what the
victim's sensitivity allows a greedy attacker at each ε — an upper reference for the manipulation
scenario, not what an attack method achieves.

    python benchmarks/steerability.py                         # every zoo victim, ε = 0.1, 10 episodes
    python benchmarks/steerability.py --victims zoo:faucet-close-v3@bc --epsilons 0.05,0.1,0.2 --episodes 20

The greedy attacker is the library's ``probe`` attack (:mod:`rat.attacks.probe`); this script measures closest
approaches beside success, for any victim, environment and steering; the tests run it on their point environment.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch

from rat.attacks.probe import greedy_delta
from rat.attacks.threat import ThreatModel
from rat.victims.base import Victim


@dataclass(frozen=True)
class Steering:
    """Where the attacker wants the victim to go.

    Attributes:
        direction: true observation -> the wanted direction in the victim's action space.
        distance: a step's ``info`` -> how far the victim is from where it should be.
        radius: success when ``distance`` falls below it.
    """

    direction: Callable[[np.ndarray], np.ndarray]
    distance: Callable[[dict], float]
    radius: float


def steerability(victim: Victim, env: gym.Env, steering: Steering, threat: ThreatModel, episodes: int,
                 restarts: int = 16, steps: int = 30, seed: int = 0) -> dict:
    """Success rate and mean closest approach of the greedily attacked victim over ``episodes``
    (episode ``i`` reset with ``seed + i``), beside the clean victim's closest approach."""
    rng = np.random.default_rng(seed)
    out = {}
    for attacked in (False, True):
        closest, hits = [], []
        for episode in range(episodes):
            obs, info = env.reset(seed=seed + episode)
            best, done = steering.distance(info), False
            while not done:
                s = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
                if attacked:
                    delta = greedy_delta(victim, obs, steering.direction(obs), threat, restarts, steps, rng)
                    s = threat.perturb(s, delta.unsqueeze(0))
                with torch.no_grad():
                    action = victim.act(s).squeeze(0).numpy()
                obs, _, terminated, truncated, info = env.step(action)
                best = min(best, steering.distance(info))
                done = terminated or truncated
            closest.append(best)
            hits.append(best < steering.radius)
        key = "attacked" if attacked else "clean"
        out[f"{key}_success"] = float(np.mean(hits))
        out[f"{key}_closest"] = float(np.mean(closest))
    return out


def reach_steering() -> Steering:
    """Meta-World's manipulation scenario: the gripper to (0.45, 0.70, 0.25), success within 5 cm."""
    from rat.envs.targets import REACH_GOAL, REACH_RADIUS

    def direction(obs: np.ndarray) -> np.ndarray:
        d = np.zeros(4)
        d[:3] = REACH_GOAL - obs[:3]  # the observation starts with the gripper's position
        return d

    return Steering(direction, lambda info: float(np.linalg.norm(np.asarray(info["tcp_pos"]) - REACH_GOAL)),
                    REACH_RADIUS)


def main() -> None:
    from rat.envs import make_task
    from rat.victims import load_victim, zoo_victims

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    every = ",".join(f"zoo:{t}@{m}" for t, ms in zoo_victims().items() for m in ms)
    parser.add_argument("--victims", default=every, help="comma-separated victim specs [every zoo victim]")
    parser.add_argument("--epsilons", default="0.1")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--restarts", type=int, default=16)
    parser.add_argument("--pgd-steps", type=int, default=30)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print("| victim | ε (ℓ∞) | greedy success | closest approach, attacked (m) | clean (m) | minutes |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for spec in args.victims.split(","):
        victim = load_victim(spec)
        for epsilon in (float(e) for e in args.epsilons.split(",")):
            started = time.perf_counter()
            r = steerability(victim, make_task(victim.meta["task"], seed=0), reach_steering(),
                             ThreatModel(epsilon, "linf"), args.episodes, args.restarts, args.pgd_steps, seed=1000)
            print(f"| {spec} | {epsilon:g} | {100 * r['attacked_success']:.0f}% ({args.episodes} ep.) | "
                  f"{r['attacked_closest']:.3f} | {r['clean_closest']:.3f} | "
                  f"{(time.perf_counter() - started) / 60:.1f} |", flush=True)


if __name__ == "__main__":
    main()
