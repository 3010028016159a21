"""Budgets of compute for a RAT run, by name, and the glue from names to a run.

- ``paper``: the paper's settings (10⁶ environment steps, batch 1024, 128 queries every 5,000
  steps): for a GPU machine and many hours.
- ``cpu``: what this project runs on a 2-core CPU machine: 50,000 environment steps, SAC and
  adversary batches of 256, the label budget spent in rounds every 5,000 steps from step 10,000 to
  90% of the run (8 rounds at 50,000 steps),
  at most 30 reward-model epochs per round, and the adversary kept at the end is the snapshot (one
  per evaluation) that the final r̂ scores best.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from rat.attacks.baselines import PPOConfig, load_attack, ppo_preset, train_baseline
from rat.attacks.rat import RATConfig, evaluate_attack, train_rat
from rat.checkpoint import read_meta
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
    total = steps or 50_000
    first, last = pebble.seed_steps + pebble.unsupervised_steps, max(pebble.seed_steps + pebble.unsupervised_steps,
                                                                      int(0.9 * total))
    rounds = (last - first) // pebble.feedback_every + 1
    per_round = max(1, -(-budget // rounds))  # ceil: the budget is spent by 90% of the run
    pebble = replace(pebble, sac=replace(pebble.sac, batch_size=256), budget=budget, per_round=per_round,
                     reward=RewardModelConfig(max_epochs=30))
    # Departure: keep the snapshot whose attack the final r̂ scores best (see RATConfig.select); short
    # CPU runs of PEBBLE are not monotone, and the attacker can judge its own attack only through r̂.
    settings = dict(total_steps=total, adversary_batch=256, weighting_every=weighting_every, pebble=pebble,
                    select="reward")
    return RATConfig(**(settings | overrides))


def _victim_and_task(victim_spec: str, target_name: str):
    target = get_target(target_name)
    victim = load_victim(victim_spec)
    task = getattr(victim, "meta", {}).get("task")
    if task is None:
        raise RatError(f"victim '{victim_spec}' does not record its task; train it with `rat victim train`")
    env_task = check_task(target.env_task(task))
    return target, victim, {"victim": victim_spec, "victim_task": task, "task": env_task}


def train_attack(victim_spec: str, target_name: str, config: RATConfig, out: str | Path, progress: bool = True,
                 tensorboard: bool = False) -> dict:
    """Train RAT against a victim given by name (``zoo:<task>``, an SB3 zip, a checkpoint)."""
    target, victim, describe = _victim_and_task(victim_spec, target_name)
    return train_rat(config, victim, target, lambda seed: make_task(describe["task"], seed=seed), out, describe,
                     progress, tensorboard)


def train_baseline_attack(method: str, victim_spec: str, target_name: str, out: str | Path, epsilon: float = 0.1,
                          norm: str = "linf", seed: int = 0, ppo: PPOConfig | None = None,
                          labels: str | Path | None = None, progress: bool = True) -> dict:
    """Train (or set up) a baseline attack against a victim given by name; see :mod:`rat.attacks.baselines`."""
    target, victim, describe = _victim_and_task(victim_spec, target_name)
    return train_baseline(method, victim, target, lambda s: make_task(describe["task"], seed=s), out, epsilon, norm,
                          seed, ppo or ppo_preset("cpu"), labels, describe=describe, progress=progress)


def evaluate_saved_attack(run: str | Path, episodes: int = 30, seed: int = 0, video: str | Path | None = None,
                          progress: bool = True, video_episodes=2) -> dict:
    """Evaluate a saved attack (RAT's or a baseline's ``<run>/adversary``) and, for comparison, the clean victim."""
    from rat.eval import evaluate

    meta = read_meta(Path(run) / "adversary" if Path(run).is_dir() else run)["meta"]
    victim = load_victim(meta["victim"])
    attack, meta = load_attack(run, victim)
    target = get_target(meta["target"])
    cfg = meta.get("rat", meta)  # RAT keeps its budget in its config, the baselines at the top level
    env = make_task(meta["task"], seed=seed, render_mode="rgb_array" if video else None)
    attacked = evaluate_attack(victim, attack, env, target, cfg["epsilon"], cfg["norm"], episodes, seed, video=video,
                               progress=progress, video_episodes=video_episodes)
    clean = evaluate(numpy_policy(victim), make_task(meta["task"], seed=seed), episodes, seed, target=target)
    return {"victim": meta["victim"], "task": meta["task"], "target": meta["target"], "method": meta["method"],
            "epsilon": cfg["epsilon"], "norm": cfg["norm"], "attack": attacked, "clean": clean}


def film_attack(run: str | Path, path: str | Path, seed: int = 0, episodes: int = 10, show: int = 2) -> list[bool]:
    """Film ``show`` of ``episodes`` attacked episodes into one video, those that reach the target first.

    Returns whether each filmed episode reached the target. The episodes are the same ones (by seed)
    in both passes, so what is filmed is what was counted.
    """
    counted = evaluate_saved_attack(run, episodes, seed, progress=False)["attack"].result.successes
    picks = ([i for i, ok in enumerate(counted) if ok] + [i for i, ok in enumerate(counted) if not ok])[:show]
    filmed = evaluate_saved_attack(run, max(picks) + 1, seed, video=path, progress=False, video_episodes=picks)
    return [filmed["attack"].result.successes[i] for i in picks]
