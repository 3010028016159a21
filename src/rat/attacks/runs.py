"""The run directory of a baseline attack: configuration, saved attack, final evaluation, report.

Every baseline (random, MAD, SA-RL, PA-AD, and a user's own) writes the same files as RAT:
``config.json``, ``metrics.csv`` while it trains, ``adversary.*`` (weights in safetensors,
metadata in JSON; loading never unpickles), and ``report.json``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym

from rat import seeds
from rat.attacks.base import AttackSetup, check_reward, get_attack
from rat.attacks.evaluation import AttackEval, evaluate_attack, evaluate_clean
from rat.attacks.threat import Perturbation
from rat.checkpoint import save_checkpoint
from rat.loop import write_report
from rat.reports import AttackReport
from rat.runs import Run, seed_everything, to_jsonable
from rat.victims.base import Victim, check_compatible

ADVERSARY_KIND = "baseline-adversary"


def baseline_run(method: str, setup: AttackSetup, out: str | Path, config: dict[str, Any],
                 train: Callable[[Run, gym.Env, Any], tuple[dict, dict]] | None = None,
                 prepare: Callable[[gym.Env], Any] | None = None, final_episodes: int = 30) -> AttackReport:
    """Check the inputs, make the run directory, train (if ``train``), save, evaluate and report.

    Args:
        method: the attack's registry name.
        config: the method's settings (JSON-able values or dataclasses, whose defaults let a run written
            before a setting existed resume), saved in ``config.json`` and the attack's metadata.
        prepare: ``env -> prepared``: work on the inputs before the run directory exists (so a
            mistake leaves nothing behind), e.g. learning r̂ from a label store.
        train: ``(run, env, prepared) -> (state, details)``: trains in the run and returns the
            tensors to save as the attack and the numbers for the report; None for attacks that
            learn nothing.
    """
    attack, seed = get_attack(method), setup.seed
    check_reward(attack, setup.reward)
    env = setup.make_env(seed)
    task = setup.describe.get("task")
    check_compatible(setup.victim, env, f"task '{task}'" if task else "the environment")
    threat = setup.threat
    settings = {"method": method, "reward": setup.reward, "epsilon": threat.epsilon, "norm": threat.norm, "seed": seed,
                "label_store": str(setup.labels) if setup.labels else None, **config, **setup.describe,
                "target": setup.target.name}
    started = time.perf_counter()
    prepared = prepare(env) if prepare is not None else None
    details: dict[str, Any] = {}
    run = Run(out, settings)
    seed_everything(seed)
    meta = {**to_jsonable(settings), "obs_dim": env.observation_space.shape[0], "act_dim": env.action_space.shape[0]}
    state: dict = {}
    if train is not None:
        state, trained = train(run, env, prepared)
        details.update(trained)
    save_checkpoint(run.dir / "adversary", ADVERSARY_KIND, state, meta)
    perturbation: Perturbation = attack.load(run.dir, meta, setup.victim)
    final = evaluate_attack(setup.victim, perturbation, setup.make_env(seed + seeds.EVAL_ENV), setup.target, threat,
                            final_episodes, seeds.FINAL)
    return conclude(run, method, setup.reward, setup, seed, final, final_episodes, steps=int(details.pop("steps", 0)),
                    labels=int(details.pop("labels", 0)), minutes=(time.perf_counter() - started) / 60,
                    train_minutes=details.pop("train_minutes", None), details=details)


def conclude(run: Run, method: str, reward: str, setup: AttackSetup, seed: int, final: AttackEval, episodes: int, *,
             steps: int, labels: int, minutes: float, train_minutes: float | None, details: dict,
             victim: Victim | None = None) -> AttackReport:
    """The end of every attack's run, RAT's and the baselines': the guard on the budget, the clean victim at the
    same target on the same episodes, and the report (returned, and written to ``run/report.json``)."""
    if not final.within_budget:  # a guard on the threat model itself, never expected to fire
        raise RuntimeError(f"perturbation {final.max_perturbation} exceeded epsilon {setup.threat.epsilon}")
    clean = evaluate_clean(victim or setup.victim, setup.make_env(seed + seeds.EVAL_ENV), setup.target, episodes,
                           seeds.FINAL, progress=setup.progress)
    report = final.report(method, reward, setup, seed, steps=steps, labels=labels, minutes=minutes,
                          train_minutes=train_minutes, details=details, clean=clean)
    write_report(run.dir, report)
    return report
