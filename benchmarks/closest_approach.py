"""How close a `reach` attack brings the gripper to the manipulation goal, beside the clean victim.

    python benchmarks/closest_approach.py RUN_DIR [EPISODES]

Prints the closest approach (metres) of the tool centre point to (0.45, 0.70, 0.25) per episode,
clean and attacked: a finer measure than success (within 5 cm) while an attack is still weak.
"""

import sys

import numpy as np

from rat.attacks import AttackedObservation, ThreatModel, load_attack
from rat.attacks.base import saved_attack_meta
from rat.envs import REACH_GOAL, make_task
from rat.victims import load_victim
from rat.victims.base import numpy_policy

run, episodes = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 5
victim = load_victim(saved_attack_meta(run)["victim"])
perturbation, meta = load_attack(run, victim)  # RAT's or any baseline's
settings = meta.get("rat", meta)
threat = ThreatModel(settings["epsilon"], settings["norm"])
victim = numpy_policy(victim)
for name, wrap in (("clean", lambda e: e), ("attacked", lambda e: AttackedObservation(e, perturbation, threat))):
    closest = []
    for ep in range(episodes):
        env = wrap(make_task(meta["task"], seed=3))
        obs, info = env.reset(seed=100 + ep)
        distances, done = [], False
        while not done:
            obs, _, terminated, truncated, info = env.step(victim(obs))
            distances.append(np.linalg.norm(info["tcp_pos"] - REACH_GOAL))
            done = terminated or truncated
        closest.append(min(distances))
    print(f"{name:9s} closest approach (m): {np.round(closest, 3).tolist()}  mean {np.mean(closest):.3f}")
