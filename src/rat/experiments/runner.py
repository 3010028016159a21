"""From names to runs: the application layer that the command line and the grids call.

``victim spec + target name + method name + preset`` becomes an :class:`~rat.attacks.AttackSetup`
and a configuration, and the registered attack trains it; a saved run is evaluated or filmed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rat.attacks.base import AttackSetup, get_attack, load_attack, saved_attack_meta, saved_attack_path
from rat.attacks.evaluation import evaluate_attack, evaluate_clean
from rat.attacks.saved import load_rat_attack
from rat.attacks.threat import ThreatModel
from rat.envs import check_task, get_target, make_task
from rat.envs.targets import TargetBehaviour
from rat.errors import RatError
from rat.experiments.presets import attack_preset
from rat.preferences.labeller import Labeller
from rat.reports import AttackReport
from rat.victims import load_victim
from rat.victims.base import Victim


def attack_setup(victim_spec: str, target_name: str, threat: ThreatModel = ThreatModel(), seed: int = 0,
                 reward: str = "labels", labels: str | Path | None = None, task: str | None = None,
                 labeller: Labeller | None = None, progress: bool = True, tensorboard: bool = False) -> AttackSetup:
    """The :class:`AttackSetup` for a victim given by name (``zoo:<task>``, an SB3 zip, a checkpoint).

    ``task`` is the victim's own task, for a victim that does not record one.
    """
    target = get_target(target_name)
    victim, task, env_task = load_victim_for(victim_spec, target, task)
    return AttackSetup(victim, target, lambda s: make_task(env_task, seed=s), threat, seed, reward,
                       Path(labels) if labels else None, labeller,
                       {"victim": victim_spec, "victim_task": task, "task": env_task}, progress, tensorboard)


def load_victim_for(victim_spec: str, target: TargetBehaviour, task: str | None = None) -> tuple[Victim, str, str]:
    """The victim of ``victim_spec``, its own task (``task``, for a victim that does not record one) and the
    task whose environment ``target`` is sought in."""
    victim = load_victim(victim_spec)
    task = task or victim.meta.get("task")
    if task is None:
        raise RatError(f"victim '{victim_spec}' does not record its task; pass --task with the task it was trained on")
    return victim, task, check_task(target.env_task(check_task(task)))


def attack_config(method: str, preset: str = "cpu", budget: int | None = None, steps: int | None = None,
                  target: str = "reach", **overrides):
    """The configuration of attack ``method`` under a named preset, with overrides of its fields."""
    return attack_preset(get_attack(method).config, preset, budget, steps, target, **overrides)


def train_attack(method: str, setup: AttackSetup, config, out: str | Path) -> AttackReport:
    """Train attack ``method`` (from the registry) with ``config``; resumable from ``out``."""
    return get_attack(method).train(setup, config, Path(out))


def evaluate_saved_attack(run: str | Path, episodes: int = 30, seed: int = 0, video: str | Path | None = None,
                          progress: bool = True, video_episodes=2, refine_steps: int | None = None,
                          refine_loss: str | None = None, lockstep: int = 32,
                          refine_switch_gap: float | None = None) -> dict:
    """Evaluate a saved attack (RAT's or a baseline's ``<run>/adversary``, or one RAT snapshot,
    ``<run>/snapshots/adversary-<step>``, with the π_θ it imitated) and, for comparison, the clean victim.

    ``refine_steps``, ``refine_loss`` and ``refine_switch_gap`` (RAT only) override the run's refinement of Δ
    towards π_θ (0 steps: the network's Δ alone); a refined attack runs ``lockstep`` episodes side by side (see
    :func:`~rat.attacks.evaluation.evaluate_attack`).
    """
    meta = saved_attack_meta(run)
    if "victim" not in meta or "task" not in meta:
        raise RatError(f"the attack in '{run}' does not record its victim and task (trained from Python with a "
                       "victim object, or its adversary.json was edited); evaluate it with rat.attacks.evaluate_attack")
    refining = (refine_steps, refine_loss, refine_switch_gap) != (None, None, None)
    if refining and meta.get("method", "rat") != "rat":
        raise RatError(f"--refine-steps, --refine-loss and --refine-switch-gap refine a RAT adversary towards its "
                       f"intention policy; '{run}' is a {meta['method']} attack: drop them")
    victim = load_victim(meta["victim"])
    gaps: list[float] = []  # the gap a refined RAT attack leaves to π_θ's action, per observation
    if meta.get("method", "rat") == "rat":  # the run, or one adversary saved in it (adversary-last[.json])
        perturbation = load_rat_attack(saved_attack_path(run), victim, refine_steps, gaps, refine_loss,
                                       refine_switch_gap)
    else:
        perturbation, meta = load_attack(run, victim)
    target = get_target(meta["target"])
    cfg = meta.get("rat", meta)  # RAT keeps its budget in its config, the baselines at the top level
    threat = ThreatModel(cfg["epsilon"], cfg["norm"])
    env = make_task(meta["task"], seed=seed, render_mode="rgb_array" if video else None)
    attacked = evaluate_attack(victim, perturbation, env, target, threat, episodes, seed, video=video,
                               progress=progress, video_episodes=video_episodes,
                               make_env=lambda: make_task(meta["task"], seed=seed), lockstep=lockstep)
    clean = evaluate_clean(victim, make_task(meta["task"], seed=seed), target, episodes, seed)
    return {"victim": meta["victim"], "task": meta["task"], "target": meta["target"],
            "method": meta.get("method", "rat"), "epsilon": threat.epsilon, "norm": threat.norm, "attack": attacked,
            "clean": clean, "refined_gap": float(np.mean(gaps)) if gaps else None,
            "snapshot_step": meta.get("snapshot_step")}


def film_attack(run: str | Path, path: str | Path, seed: int = 0, episodes: int = 10, show: int = 2) -> list[bool]:
    """Film ``show`` of ``episodes`` attacked episodes into one video, those that reach the target first.

    Returns whether each filmed episode reached the target. The episodes are the same ones (by seed)
    in both passes, so what is filmed is what was counted.
    """
    counted = evaluate_saved_attack(run, episodes, seed, progress=False)["attack"].result.successes
    picks = ([i for i, ok in enumerate(counted) if ok] + [i for i, ok in enumerate(counted) if not ok])[:show]
    filmed = evaluate_saved_attack(run, max(picks) + 1, seed, video=path, progress=False, video_episodes=picks)
    return [filmed["attack"].result.successes[i] for i in picks]
