"""Where a RAT run's time goes, per 1,000 environment steps, with the `cpu` preset.

    python benchmarks/rat_profile.py [--labels 9000] [--victim zoo:faucet-close-v3] [--target reach] > benchmarks/rat_profile.md

Each component is timed as the RAT loop runs it (median of repeats after a warm-up), then scaled
to its frequency per 1,000 steps: 1,000 environment steps with the victim's or intention
policy's action, the intention policy's SAC updates (1,000 at one a step), the adversary and weighting updates the preset schedules
(for `reach`: 100 and one), and one reward round (training plus relabelling) every 5,000. A sequence
victim (a Decision Transformer) is timed with full-length contexts: the stored ones are a fresh
episode's, all padding, which costs the model the same as a full history.
The timed round trains on all ``--labels`` labels at once, as the run's last round does: the
costliest round, so the reward model's share is an upper bound.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

from rat.attacks.rat import RATTrainer
from rat.experiments.presets import rat_config
from rat.experiments.runner import attack_setup
from rat.preferences.store import LabelStore
from rat.preferences.teacher import ScriptedTeacher


def timed(fn, repeats: int, warmup: int = 2) -> float:
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t)
    return statistics.median(samples)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--labels", type=int, default=9000, help="labels held in the timed reward round "
                        "(the paper's 9,000 for a manipulation row)")
    parser.add_argument("--victim", default="zoo:faucet-close-v3")
    parser.add_argument("--target", default="reach")
    args = parser.parse_args()
    torch.set_num_threads(1)

    cfg = rat_config("cpu", budget=args.labels)
    setup = attack_setup(args.victim, args.target, cfg.threat, progress=False)
    env, target = setup.make_env(0), setup.target
    tmp = tempfile.mkdtemp()
    rat = RATTrainer(cfg, setup, env, LabelStore(f"{tmp}/labels.sqlite"), "profile", Path(tmp) / "snapshots")
    learner, rng = rat.learner, rat.rng

    obs, _ = env.reset(seed=0)
    env.action_space.seed(0)
    for _ in range(10_000):  # fill the buffer and history with real transitions
        action = env.action_space.sample()
        nxt, _, term, trunc, info = env.step(action)
        learner.buffer.add(obs, action, 0.0, nxt, term)
        learner.history.add(obs, action, target.reward(obs, action, nxt, info), term or trunc)
        obs = env.reset()[0] if term or trunc else nxt

    def env_steps():
        o, _ = env.reset(seed=1)
        for t in range(1000):
            a = rat.victim_policy(rat.perturbed(o)) if t % 2 else learner.agent.act(o)
            o, _, term, trunc, info = env.step(a)
            target.reward(o, a, o, info)
            if term or trunc:
                o, _ = env.reset()

    adversary = 1000 / cfg.adversary_every * cfg.adversary_updates  # per 1,000 steps, as the run schedules them
    weighting = 1000 / cfg.weighting_every
    sac = 1000 * cfg.pebble.updates_per_step
    rows = {
        "environment (1,000 steps, acting included)": timed(env_steps, 3, 1),
        f"intention SAC ({sac:,g} updates, batch {cfg.pebble.sac.batch_size})": sac * timed(lambda: learner.update(), 50, 5),
        f"adversary ({adversary:g} updates, batch {cfg.adversary_batch})": adversary * timed(rat.adversary_step, 30),
        f"weighting network ({weighting:g} hypergradient update{'s' if weighting != 1 else ''}, batch {cfg.adversary_batch})":
            weighting * timed(rat.weighting_step, 10),
    }
    teacher = ScriptedTeacher()
    pairs = learner.history.sample_pairs(args.labels, 50, rng)
    labels = teacher.label(pairs, rng)

    def reward_round():
        learner.ensemble.train_round(pairs.obs0, pairs.act0, pairs.obs1, pairs.act1, labels.y, rng)
        learner.buffer.relabel(lambda o, a, _: learner.ensemble.r_hat(o, a))

    epochs, updates = cfg.pebble.reward.max_epochs, cfg.pebble.reward.max_updates
    rows[f"reward model (1/5 of a round: {args.labels:,} labels, ≤ {epochs} epochs and ≤ {updates} updates a "
         "member, relabel 10k)"] = timed(reward_round, 1, 0) / 5
    total = sum(rows.values())
    print("# Where the time goes: RAT, `cpu` preset, per 1,000 environment steps\n")
    print(f"Measured by `python benchmarks/rat_profile.py --labels {args.labels} --victim {args.victim} --target "
          f"{args.target}` on this project's 2-core CPU machine, torch on one")
    print("thread (medians after warm-up; the machine is shared and noisy).\n")
    print("| component | seconds per 1,000 steps | share |")
    print("| --- | ---: | ---: |")
    for name, sec in rows.items():
        print(f"| {name} | {sec:.2f} | {100 * sec / total:.0f}% |")
    print(f"| **total** | **{total:.2f}** | |")
    print(f"\nAt this rate 50,000 steps take about {50 * total / 60:.0f} minutes; 1,000,000 about {1000 * total / 3600:.1f} hours.")
    print(f"Reward-model epochs run in the timed round: {learner.ensemble.epochs_run}.")


if __name__ == "__main__":
    main()
