"""What an update costs: our SAC update against Stable-Baselines3's and against an earlier commit, and a
reward-model round before and after, all in one process, interleaved, one torch thread
(recorded in ``benchmarks/speed.md``).

    git worktree add /tmp/rat-base 5e176f0 --detach     # the code to compare against
    python benchmarks/speed.py --base /tmp/rat-base/src [--sac-only | --reward-only] [--labels 1000 3000 9000]

SAC: each variant makes ``--updates`` updates in turn, ``--repeats`` times round-robin, so the machine's
moods fall on all of them alike; the figure is the median milliseconds per update (buffer sampling
included: ours draws from our replay buffer, SB3's from its own, as each agent's training loop does).
The networks are the same for all: 3×256 ReLU layers, a 39-d observation and a 4-d action (Meta-World).

Reward round: the round a run makes last, warm: the ensemble first trains on the labels less one round's
worth (one eighth, as the ``cpu`` preset's eight rounds make), then the timed round holds them all. Labels
come from the scripted teacher on segments of 10,000 random-action steps of faucet-close-v3, scored by the
``reach`` target; each round's quality is the ensemble's accuracy on 2,000 further labelled pairs.
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import sys
import time
from dataclasses import replace

import numpy as np
import torch

OBS, ACT = 39, 4


def import_base(src: str) -> dict:
    """The classes of the ``rat`` package under ``src`` (an earlier commit's), imported beside this one's."""
    saved = {k: v for k, v in sys.modules.items() if k == "rat" or k.startswith("rat.")}
    for k in saved:
        del sys.modules[k]
    sys.path.insert(0, src)
    try:
        sac = importlib.import_module("rat.agents.sac")
        reward = importlib.import_module("rat.preferences.reward_model")
        base = {"SAC": sac.SAC, "SACConfig": sac.SACConfig, "RewardEnsemble": reward.RewardEnsemble,
                "RewardModelConfig": reward.RewardModelConfig, "file": sac.__file__}
    finally:
        sys.path.remove(src)
        for k in [k for k in sys.modules if k == "rat" or k.startswith("rat.")]:
            del sys.modules[k]
        sys.modules.update(saved)
    return base


def fill(add, n: int = 20_000, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(n):
        add(rng.standard_normal(OBS).astype(np.float32), rng.uniform(-1, 1, ACT).astype(np.float32),
            float(rng.standard_normal()), rng.standard_normal(OBS).astype(np.float32), False)


def ours(sac_cls, config_cls, batch: int, **settings):
    from rat.agents.buffer import ReplayBuffer

    torch.manual_seed(0)
    agent = sac_cls(OBS, ACT, config_cls(batch_size=batch, **settings))
    buffer, rng = ReplayBuffer(OBS, ACT, 20_000), np.random.default_rng(0)
    fill(buffer.add)

    def run(k: int) -> None:
        for _ in range(k):
            agent.update(buffer.sample(batch, rng))
    run.agent = agent
    return run


def sb3(batch: int):
    import gymnasium as gym
    from stable_baselines3 import SAC as SB3SAC

    class Box(gym.Env):  # only its spaces are read: the updates draw from the filled buffer
        observation_space = gym.spaces.Box(-np.inf, np.inf, (OBS,), np.float32)
        action_space = gym.spaces.Box(-1, 1, (ACT,), np.float32)

    model = SB3SAC("MlpPolicy", Box(), batch_size=batch, learning_rate=1e-4, buffer_size=20_000, device="cpu",
                   policy_kwargs={"net_arch": [256, 256, 256]}, seed=0)
    model._logger = __import__("stable_baselines3.common.logger", fromlist=["x"]).configure(None, [""])
    fill(lambda o, a, r, n, d: model.replay_buffer.add(o[None], n[None], a[None], np.array([r]), np.array([d]), [{}]))

    def run(k: int) -> None:
        model.train(gradient_steps=k, batch_size=batch)
    return run


def interleaved(variants: dict, updates: int, repeats: int) -> dict[str, float]:
    for run in variants.values():  # warm-up
        run(20)
    times = {name: [] for name in variants}
    for _ in range(repeats):
        for name, run in variants.items():
            started = time.perf_counter()
            run(updates)
            times[name].append(1000 * (time.perf_counter() - started) / updates)
    return {name: statistics.median(t) for name, t in times.items()}


def sac_table(base: dict | None, batches: list[int], updates: int, repeats: int) -> None:
    from rat.agents.sac import SAC, SACConfig

    print("### SAC update, milliseconds (median of interleaved repeats)\n")
    names = ["SB3 SAC", *(["starting commit"] if base else []), "ours, fp32", "ours, bf16"]
    print("| batch | " + " | ".join(names) + " | bf16 vs SB3 | bf16 vs starting commit | fp32 vs starting commit |")
    print("| ---: |" + " ---: |" * (len(names) + 3))
    for batch in batches:
        variants = {"SB3 SAC": sb3(batch)}
        if base:
            variants["starting commit"] = ours(base["SAC"], base["SACConfig"], batch)
        variants["ours, fp32"] = ours(SAC, SACConfig, batch)
        variants["ours, bf16"] = ours(SAC, SACConfig, batch, precision="bf16")
        ms = interleaved(variants, updates, repeats)
        old = ms.get("starting commit", float("nan"))
        print(f"| {batch} | " + " | ".join(f"{ms[n]:.1f}" for n in names) +
              f" | {ms['SB3 SAC'] / ms['ours, bf16']:.2f}× | {old / ms['ours, bf16']:.2f}× | {old / ms['ours, fp32']:.2f}× |",
              flush=True)
    print()


def same_as_base(base: dict, steps=(1, 10, 100, 300)) -> None:
    """The defaults (fp32 SAC, PEBBLE's rounds) against the starting commit's from equal seeds: the largest
    weight difference after a number of updates, beside our own code with fused Adam against unfused Adam.
    Where the two rows agree, fused Adam's summation order is all that differs."""
    from rat.agents.sac import SAC, SACConfig
    from rat.preferences.reward_model import RewardEnsemble, RewardModelConfig

    def unfused(run):
        for optimizer in (run.agent.actor_opt, run.agent.critic_opt, run.agent.alpha_opt):
            for group in optimizer.param_groups:
                group["fused"] = None
        return run

    def gap(make_a, make_b, n: int) -> float:
        agents = []
        for make in (make_a, make_b):
            run = make()
            torch.manual_seed(1)  # the actor's samples: the same draws for both
            run(n)
            agents.append(run.agent)
        return max(float((p - q).detach().abs().max()) for p, q in zip(*(a.parameters() for a in agents)))

    print("### Same results as the starting commit (defaults, equal seeds)\n")
    print("Largest difference of any SAC weight (actor, critics, temperature; batch 256):\n")
    print("| compared | " + " | ".join(f"after {n}" for n in steps) + " |")
    print("| --- |" + " ---: |" * len(steps))
    rows = {"starting commit vs this code": (lambda: ours(base["SAC"], base["SACConfig"], 256),
                                             lambda: ours(SAC, SACConfig, 256)),
            "this code: unfused vs fused Adam": (lambda: unfused(ours(SAC, SACConfig, 256)),
                                                 lambda: ours(SAC, SACConfig, 256))}
    for name, (make_a, make_b) in rows.items():
        print(f"| {name} | " + " | ".join(f"{gap(make_a, make_b, n):.1e}" for n in steps) + " |")
    pairs, y = labelled_pairs(1000, seed=0)
    ensembles = []
    for ensemble_cls, config_cls in ((base["RewardEnsemble"], base["RewardModelConfig"]),
                                     (RewardEnsemble, RewardModelConfig)):
        torch.manual_seed(0)
        ensemble = ensemble_cls(OBS, ACT, config_cls(max_epochs=5, max_updates=100, normalize_inputs=True))
        ensemble.train_round(pairs.obs0, pairs.act0, pairs.obs1, pairs.act1, y, np.random.default_rng(0))
        ensembles.append(ensemble)
    old, new = (dict(e.nets.named_parameters()) for e in ensembles)
    diff = max(float((old[k] - new[k]).detach().abs().max()) for k in old)
    print(f"\nReward ensemble, one round on 1,000 labels (100 updates a member): largest weight difference "
          f"{diff:.1e} (largest weight {max(float(v.detach().abs().max()) for v in new.values()):.2f}).\n")


def labelled_pairs(n: int, seed: int):
    """``n`` scripted labels of 50-step segments of random-action faucet-close-v3, by ``reach``."""
    from rat.experiments.presets import rat_config
    from rat.experiments.runner import attack_setup
    from rat.preferences.segments import EpisodeHistory
    from rat.preferences.teacher import ScriptedTeacher

    setup = attack_setup("zoo:faucet-close-v3", "reach", rat_config("cpu").threat, progress=False)
    env, target = setup.make_env(seed), setup.target
    history, rng = EpisodeHistory(), np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    env.action_space.seed(seed)
    for _ in range(10_000):
        action = env.action_space.sample()
        nxt, _, term, trunc, info = env.step(action)
        history.add(obs, action, target.reward(obs, action, nxt, info), term or trunc)
        obs = env.reset()[0] if term or trunc else nxt
    pairs = history.sample_pairs(n, 50, rng)
    return pairs, ScriptedTeacher().label(pairs, rng).y


def reward_table(base: dict | None, label_counts: list[int]) -> None:
    from rat.experiments.presets import rat_config
    from rat.preferences.reward_model import RewardEnsemble

    before = rat_config("cpu").pebble.reward  # the cpu preset's round (the starting commit's)
    after = replace(before, holdout=0.1, precision="bf16")
    test, test_y = labelled_pairs(2000, seed=1)
    pairs, y = labelled_pairs(max(label_counts), seed=0)
    print("### Reward-model round, seconds (the run's last round, warm), and test accuracy of r̂\n")
    print(f"Before: {before.members} members, ≤ {before.max_epochs} epochs and ≤ {before.max_updates} updates a member "
          f"on every label; after: held-out rounds in bf16 ({after}).\n")
    print("| labels | before: s | updates a member | test accuracy | after: s | updates a member | test accuracy | cheaper |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")

    def accuracy(ensemble) -> float:
        p = ensemble.preference_probabilities(test.obs0, test.act0, test.obs1, test.act1).mean(0)
        return float((((p > 0.5) == (test_y > 0.5)) | (test_y == 0.5)).mean())

    for n in label_counts:
        row = []
        for ensemble_cls, config_cls, config in (
                (base["RewardEnsemble"], base["RewardModelConfig"], None) if base else (RewardEnsemble, None, before),
                (RewardEnsemble, None, after)):
            if config is None:  # the base's own config class, with the settings it knew
                config = config_cls(max_epochs=before.max_epochs, max_updates=before.max_updates,
                                    normalize_inputs=before.normalize_inputs)
            torch.manual_seed(0)
            ensemble, rng = ensemble_cls(OBS, ACT, config), np.random.default_rng(0)
            m = n - n // 8
            ensemble.train_round(pairs.obs0[:m], pairs.act0[:m], pairs.obs1[:m], pairs.act1[:m], y[:m], rng)
            started = time.perf_counter()
            metrics = ensemble.train_round(pairs.obs0[:n], pairs.act0[:n], pairs.obs1[:n], pairs.act1[:n], y[:n], rng)
            row.append((time.perf_counter() - started, metrics["reward_updates"], accuracy(ensemble)))
        (t0, u0, a0), (t1, u1, a1) = row
        print(f"| {n:,} | {t0:.1f} | {u0:.0f} | {a0:.3f} | {t1:.1f} | {u1:.0f} | {a1:.3f} | {t0 / t1:.1f}× |", flush=True)
    print()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", help="src/ of the commit to compare against (a git worktree's)")
    parser.add_argument("--batches", type=int, nargs="+", default=[256, 1024])
    parser.add_argument("--updates", type=int, default=25, help="updates per variant per turn")
    parser.add_argument("--repeats", type=int, default=12)
    parser.add_argument("--labels", type=int, nargs="+", default=[1000, 3000, 9000])
    parser.add_argument("--sac-only", action="store_true")
    parser.add_argument("--reward-only", action="store_true")
    parser.add_argument("--same-only", action="store_true", help="only the equal-seeds check against --base")
    args = parser.parse_args()
    torch.set_num_threads(1)
    base = import_base(args.base) if args.base else None
    import rat
    print(f"torch {torch.__version__}, one thread; this code: {rat.__file__}; base: {base['file'] if base else 'none'}\n")
    if base:
        same_as_base(base)
    if args.same_only:
        return
    if not args.reward_only:
        sac_table(base, args.batches, args.updates, args.repeats)
    if not args.sac_only:
        reward_table(base, args.labels)


if __name__ == "__main__":
    main()
