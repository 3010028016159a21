"""Refining Δ against a Decision Transformer: the time per observation with the context prepared once, and without.

Refinement takes ``--steps`` Adam steps on one observation's Δ, each a pass of the victim forwards and
backwards, in a context that does not change meanwhile. Prepared (``DecisionTransformerVictim.prepare``),
the context's 58 past tokens run through the transformer once per observation; unprepared, once per step.
The networks here are untrained (the adversary's and π_θ's weights do not change the cost); the contexts
are real: the zoo victim's own episode on HalfCheetah-v5.

    python benchmarks/dt_refine_speed.py --observations 20 --steps 50

Prints seconds per observation for each mode and batch size, and the largest difference in Δ between
the two modes. Results are recorded in ``benchmarks/rat_profile.md``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from rat.agents.networks import TanhGaussianActor
from rat.attacks.losses import Adversary
from rat.attacks.refine import refined_function
from rat.attacks.threat import ThreatModel
from rat.envs import make_task
from rat.victims import load_victim
from rat.victims.base import VictimPolicy


def episode_observations(victim, count: int, seed: int) -> np.ndarray:
    """The first ``count`` observations of the victim's own clean episode."""
    env, policy = make_task("HalfCheetah-v5", seed=seed), VictimPolicy(victim)
    obs, _ = env.reset(seed=seed)
    policy.reset()
    seen = []
    for _ in range(count):
        seen.append(obs)
        obs, reward, *_ = env.step(policy(obs))
        policy.observe(reward)
    return np.asarray(seen)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--observations", type=int, default=20)
    parser.add_argument("--steps", type=int, default=50, help="refinement steps per observation")
    parser.add_argument("--batches", default="1,8", help="episodes refined together (lockstep widths)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    victim = load_victim("zoo:dt/halfcheetah-v5")
    obs_dim, act_dim = victim.observation_space.shape[0], victim.action_space.shape[0]
    adversary, intention = Adversary(obs_dim), TanhGaussianActor(obs_dim, act_dim)
    observations = episode_observations(victim, args.observations, args.seed)
    chosen = {}
    for width in (int(w) for w in args.batches.split(",")):
        for mode in ("prepared", "unprepared"):
            if mode == "unprepared":
                victim.prepare = lambda context: context  # act in the plain context: the past again at every step
            attack = refined_function(adversary, intention, victim, ThreatModel(0.1), args.steps)
            deltas, start = [], time.perf_counter()
            for obs in observations:  # ``width`` episodes side by side, each seeing this observation after its own past
                deltas.append(attack.batch(np.repeat(obs[None], width, 0), list(range(width))))
                for slot in range(width):
                    attack.observe(obs + 0.1 * deltas[-1][slot], np.zeros(act_dim), 1.0, slot)
            seconds = (time.perf_counter() - start) / len(observations)
            chosen[mode] = np.asarray(deltas)
            if mode == "unprepared":
                del victim.prepare
            print(f"{width} episode(s), {mode}: {seconds:.3f} s per observation", flush=True)
        print(f"  largest difference in Δ between the modes: {np.abs(chosen['prepared'] - chosen['unprepared']).max():.2e}")


if __name__ == "__main__":
    main()
