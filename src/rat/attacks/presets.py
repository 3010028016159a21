"""Budgets of compute for a RAT run, by name, and the glue from names to a run.

- ``paper``: the paper's settings (10⁶ environment steps, batch 1024, 128 queries every 5,000
  steps): for a GPU machine and many hours.
- ``cpu``: what this project runs on a 2-core CPU machine: 50,000 environment steps, SAC and
  adversary batches of 256, the label budget spent in 8 rounds between steps 10,000 and 45,000,
  at most 30 reward-model epochs per round.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from rat.attacks.rat import RATConfig, adversary_function, evaluate_attack, load_adversary, train_rat
from rat.envs import check_task, get_target, make_task
from rat.errors import RatError
from rat.preferences.pebble import PebbleConfig
from rat.preferences.reward_model import RewardModelConfig
from rat.victims import load_victim
from rat.victims.base import numpy_policy

PRESETS = ("cpu", "paper")


def rat_config(preset: str = "cpu", budget: int = 3000, steps: int | None = None, target: str = "reach",
               **overrides) -> RATConfig:
    """A :class:`RATConfig` from a preset, a label budget and overrides of any field."""
    if preset not in PRESETS:
        raise RatError(f"unknown preset '{preset}'; use one of: {', '.join(PRESETS)}")
    pebble = PebbleConfig()
    weighting_every = 1000 if target == "reach" else 2000  # the released schedule: manipulation vs opposite
    if preset == "paper":
        settings = dict(total_steps=steps or 1_000_000, weighting_every=weighting_every,
                        pebble=replace(pebble, budget=budget))
        return RATConfig(**(settings | overrides))
    first, last = pebble.seed_steps + pebble.unsupervised_steps, 45_000
    rounds = (last - first) // pebble.feedback_every + 1
    per_round = max(1, -(-budget // rounds))  # ceil: the budget is spent by step 45,000
    pebble = replace(pebble, sac=replace(pebble.sac, batch_size=256), budget=budget, per_round=per_round,
                     reward=RewardModelConfig(max_epochs=30))
    settings = dict(total_steps=steps or 50_000, adversary_batch=256, weighting_every=weighting_every, pebble=pebble)
    return RATConfig(**(settings | overrides))


def train_attack(victim_spec: str, target_name: str, config: RATConfig, out: str | Path, progress: bool = True,
                 tensorboard: bool = False) -> dict:
    """Train RAT against a victim given by name (``zoo:<task>``, an SB3 zip, a checkpoint)."""
    target = get_target(target_name)
    victim = load_victim(victim_spec)
    task = getattr(victim, "meta", {}).get("task")
    if task is None:
        raise RatError(f"victim '{victim_spec}' does not record its task; train it with `rat victim train`")
    env_task = check_task(target.env_task(task))
    describe = {"victim": victim_spec, "victim_task": task, "task": env_task}
    return train_rat(config, victim, target, lambda seed: make_task(env_task, seed=seed), out, describe, progress,
                     tensorboard)


def evaluate_saved_attack(run: str | Path, episodes: int = 30, seed: int = 0, video: str | Path | None = None,
                          progress: bool = True) -> dict:
    """Evaluate a trained adversary (``<run>/adversary``) and, for comparison, the clean victim."""
    from rat.eval import evaluate

    adversary, meta = load_adversary(run)
    target, victim = get_target(meta["target"]), load_victim(meta["victim"])
    cfg = meta["rat"]
    env = make_task(meta["task"], seed=seed, render_mode="rgb_array" if video else None)
    attacked = evaluate_attack(victim, adversary_function(adversary), env, target, cfg["epsilon"], cfg["norm"],
                               episodes, seed, video=video, progress=progress)
    clean = evaluate(numpy_policy(victim), make_task(meta["task"], seed=seed), episodes, seed, target=target)
    return {"victim": meta["victim"], "task": meta["task"], "target": meta["target"], "epsilon": cfg["epsilon"],
            "norm": cfg["norm"], "attack": attacked, "clean": clean}
