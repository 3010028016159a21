"""Evaluating an attack: the attacked victim's target success, and the size of every perturbation."""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import gymnasium as gym
import numpy as np

from rat.attacks.threat import AttackedObservation, Perturbation, ThreatModel
from rat.envs.targets import TargetBehaviour
from rat.eval import EvalResult, evaluate
from rat.reports import AttackReport
from rat.victims.base import Victim, numpy_policy


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
            clean_success_rate=None if clean is None else clean.success_rate)


def evaluate_attack(victim: Victim, perturbation: Perturbation, env: gym.Env, target: TargetBehaviour,
                    threat: ThreatModel, episodes: int, seed: int, *, video: str | Path | None = None,
                    video_episodes: int | Sequence[int] = 2, progress: bool = False,
                    desc: str = "evaluating the attack") -> AttackEval:
    """Run the victim on attacked observations; success is the *target*'s test, at any step.

    Episode ``i`` is reset with ``seed + i`` (see :mod:`rat.seeds`).
    """
    attacked = AttackedObservation(env, perturbation, threat)
    result = evaluate(numpy_policy(victim), attacked, episodes, seed, target=target, video=video, progress=progress,
                      video_episodes=video_episodes, desc=desc)
    norms = np.asarray(attacked.norms)
    return AttackEval(result, threat, float(norms.max()), float(norms.mean()), len(norms), list(attacked.records))


def evaluate_clean(victim: Victim, env: gym.Env, target: TargetBehaviour, episodes: int, seed: int,
                   progress: bool = False) -> EvalResult:
    """The unattacked victim's success at ``target`` over the episodes :func:`evaluate_attack` runs with ``seed``."""
    return evaluate(numpy_policy(victim), env, episodes, seed, target=target, progress=progress,
                    desc="the clean victim")
