"""Evaluating an attack: the attacked victim's target success, and the size of every perturbation."""

from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from tqdm.auto import tqdm

from rat.attacks.threat import AttackedObservation, Perturbation, ThreatModel
from rat.envs.targets import TargetBehaviour
from rat.eval import EvalResult, evaluate
from rat.reports import AttackReport
from rat.victims.base import Victim, is_sequence, numpy_policy, victim_device


@dataclass
class AttackEval:
    """An attack's evaluation: the target success of the attacked victim, and perturbation sizes."""

    result: EvalResult
    threat: ThreatModel
    max_perturbation: float
    mean_perturbation: float
    steps: int
    records: list[tuple[int, int, float]] = field(default_factory=list)  #: (episode, step, norm) of every observation

    @property
    def within_budget(self) -> bool:
        return self.max_perturbation <= self.threat.epsilon * (1 + 1e-6) + 1e-12

    def write_records(self, path: str | Path) -> Path:
        """Every perturbation's size, one CSV row per observation the victim saw: an audit of the budget."""
        path = Path(path)
        with open(path, "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["episode", "step", "norm", "epsilon", "within_budget"])
            bound = self.threat.epsilon * (1 + 1e-6) + 1e-12
            writer.writerows((e, t, repr(n), self.threat.epsilon, int(n <= bound)) for e, t, n in self.records)
        return path

    def summary(self) -> str:
        return (f"{self.result.summary()}; perturbation {self.threat.norm} mean {self.mean_perturbation:.4f}, "
                f"max {self.max_perturbation:.4f} <= {self.threat}")

    def report(self, method: str, reward: str, setup, seed: int, *, steps: int = 0, labels: int = 0,
               minutes: float = 0.0, train_minutes: float | None = None, details: dict | None = None,
               clean: EvalResult | None = None) -> AttackReport:
        """The run's :class:`~rat.reports.AttackReport` with this as its final evaluation.

        ``minutes`` is this call's, ``train_minutes`` training's over every session (default: ``minutes``).
        ``clean`` is the unattacked victim on the same target and episodes (:func:`evaluate_clean`):
        the yardstick that says whether the attack did anything.
        """
        d = setup.describe
        return AttackReport(
            method=method, reward=reward, victim=d.get("victim", setup.victim.name), task=d.get("task", "?"),
            target=setup.target.name, epsilon=self.threat.epsilon, norm=self.threat.norm, seed=seed,
            attack_success_rate=self.result.success_rate, attack_success_ci=list(self.result.success_ci),
            episodes=self.result.episodes, max_perturbation=self.max_perturbation,
            mean_perturbation=self.mean_perturbation, steps=steps, labels=labels, victim_task=d.get("victim_task"),
            train_minutes_this_session=round(minutes, 2),
            train_minutes=round(minutes if train_minutes is None else train_minutes, 2), details=details or {},
            clean_success_rate=None if clean is None else clean.success_rate, attacked_return=self.result.mean_return,
            clean_return=None if clean is None else clean.mean_return)


def evaluate_attack(victim: Victim, perturbation: Perturbation, env: gym.Env, target: TargetBehaviour,
                    threat: ThreatModel, episodes: int, seed: int, *, video: str | Path | None = None,
                    video_episodes: int | Sequence[int] = 2, progress: bool = False,
                    desc: str = "evaluating the attack", make_env: Callable[[], gym.Env] | None = None,
                    lockstep: int = 32) -> AttackEval:
    """Run the victim on attacked observations; success is the *target*'s test, at any step.

    Episode ``i`` is reset with ``seed + i`` (see :mod:`rat.seeds`). Given ``make_env`` (more environments
    like ``env``), a perturbation that computes many observations' Δ at once (``batch``: a refined RAT
    attack), up to ``lockstep`` episodes run side by side and each step's Δ and actions are computed for
    all of them together: the same episodes and numbers but for floating-point rounding, in a fraction of
    the time (a video is always made one episode at a time). A sequence victim keeps each episode's context.
    """
    if make_env is not None and video is None and hasattr(perturbation, "batch") and lockstep > 1:
        return _evaluate_in_lockstep(victim, perturbation, env, make_env, target, threat, episodes, seed,
                                     lockstep, progress, desc)
    attacked = AttackedObservation(env, perturbation, threat)
    result = evaluate(numpy_policy(victim), attacked, episodes, seed, target=target, video=video, progress=progress,
                      video_episodes=video_episodes, desc=desc)
    norms = np.asarray(attacked.norms)
    return AttackEval(result, threat, float(norms.max()), float(norms.mean()), len(norms), list(attacked.records))


def _evaluate_in_lockstep(victim: Victim, perturbation, env: gym.Env, make_env: Callable[[], gym.Env],
                          target: TargetBehaviour, threat: ThreatModel, episodes: int, seed: int, width: int,
                          progress: bool, desc: str) -> AttackEval:
    """:func:`evaluate_attack` with ``width`` episodes at a time, Δ and actions computed for them together.

    Each episode sees exactly what it would alone: reset with ``seed + i``, every observation perturbed
    once (the one after the last step too, as :class:`AttackedObservation` does), its success test its own,
    a sequence victim's context its own (stacked into one batch for each step's actions), and a perturbation
    with ``observe`` told each of its steps as :class:`AttackedObservation` tells it (with the episode's slot).
    """
    envs = [env] + [make_env() for _ in range(min(width, episodes) - 1)]
    device = victim_device(victim)
    contexts = {} if is_sequence(victim) else None  # per slot, as VictimPolicy keeps one
    returns, first, last = [0.0] * episodes, [-1] * episodes, [False] * episodes
    records: list[tuple[int, int, float]] = []
    with tqdm(total=episodes, desc=desc, disable=not progress, leave=False) as bar:
        for start in range(0, episodes, len(envs)):
            wave = range(start, min(start + len(envs), episodes))  # episode start + k runs in envs[k]
            obs, tests, steps, ended = {}, {}, {}, set()
            for k, episode in enumerate(wave):
                if hasattr(perturbation, "reset"):
                    perturbation.reset(k)
                obs[k] = envs[k].reset(seed=seed + episode)[0]
                tests[k], steps[k] = target.episode_success(), 0
                if contexts is not None:
                    contexts[k] = victim.initial_context(1)
            while obs:
                slots = sorted(obs)
                true = np.stack([obs[k] for k in slots])
                delta = torch.as_tensor(perturbation.batch(true, slots), dtype=torch.float64)
                attacked = threat.perturb(torch.as_tensor(true, dtype=torch.float64), delta).numpy()
                norms = threat.size(attacked - true)
                records.extend((wave[k], steps[k], float(n)) for k, n in zip(slots, norms))
                for k in [k for k in slots if k in ended]:  # its last observation is perturbed, not acted on
                    del obs[k]
                    bar.update(1)
                acting = [i for i, k in enumerate(slots) if k not in ended]
                if not acting:
                    continue
                with torch.no_grad():
                    seen = torch.as_tensor(attacked[acting].astype(true.dtype), dtype=torch.float32, device=device)
                    context = None if contexts is None else victim.unpack_context(
                        torch.cat([victim.pack_context(contexts[slots[i]]) for i in acting]))
                    taken = victim.act(seen, context)
                    actions = taken.cpu().numpy()
                for row, (i, action) in enumerate(zip(acting, actions)):
                    k = slots[i]
                    obs[k], reward, terminated, truncated, info = envs[k].step(action)
                    if contexts is not None:
                        contexts[k] = victim.update_context(contexts[k], seen[row:row + 1], taken[row:row + 1],
                                                            torch.tensor([float(reward)]))
                    if hasattr(perturbation, "observe"):
                        perturbation.observe(attacked[i].astype(true.dtype), action, reward, slot=k)
                    episode = wave[k]
                    returns[episode] += reward
                    last[episode] = tests[k](info)
                    if last[episode] and first[episode] < 0:
                        first[episode] = steps[k]
                    steps[k] += 1
                    if terminated or truncated:
                        ended.add(k)
    for extra in envs[1:]:
        extra.close()
    result = EvalResult.of(returns, first, last)
    records.sort()
    norms = np.array([n for _, _, n in records])
    return AttackEval(result, threat, float(norms.max()), float(norms.mean()), len(norms), records)


def evaluate_clean(victim: Victim, env: gym.Env, target: TargetBehaviour, episodes: int, seed: int,
                   progress: bool = False) -> EvalResult:
    """The unattacked victim's success at ``target`` over the episodes :func:`evaluate_attack` runs with ``seed``."""
    return evaluate(numpy_policy(victim), env, episodes, seed, target=target, progress=progress,
                    desc="the clean victim")
