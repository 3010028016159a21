"""Typed results: what a run writes to ``report.json`` and what reads it back.

A report is a dataclass: fields every reader relies on are named and typed; what is one
method's own (RAT's update counts, a baseline's reward-model accuracy) goes in ``details``.
Reading a report written by an older version puts keys it does not know into ``details``.
"""

from __future__ import annotations

import json
from dataclasses import MISSING, asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from rat.errors import RatError


def _read(cls, path: str | Path):
    path = Path(path)
    path = path / "report.json" if path.is_dir() else path
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise RatError(f"no report at '{path}': the run has not finished; run it again to resume") from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise RatError(f"report '{path}' is corrupted ({exc.__class__.__name__}); run the run again to rewrite it") from exc
    if not isinstance(data, dict):
        raise RatError(f"report '{path}' is not a JSON object; run the run again to rewrite it")
    return cls.from_dict(data)


class _Report:
    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]):
        names = {f.name for f in fields(cls)}
        known = {k: v for k, v in data.items() if k in names and k != "details"}
        details = {**data.get("details", {}), **{k: v for k, v in data.items() if k not in names}}
        missing = [f.name for f in fields(cls) if f.name not in known and f.default is MISSING
                   and f.default_factory is MISSING]
        if missing:
            raise RatError(f"report lacks {', '.join(missing)}; it was not written by rat: run the run again")
        return cls(**known, details=details)

    @classmethod
    def read(cls, path: str | Path):
        """The report of a run directory (or a ``report.json`` path)."""
        return _read(cls, path)


@dataclass
class AttackReport(_Report):
    """The outcome of training an attack and evaluating it (``<run>/report.json``).

    Attributes:
        method: the attack's registry name (``rat``, ``random``, ``sa-rl``, ...).
        reward: what it learned from: ``labels`` (preference labels), ``oracle`` (the true target
            reward) or ``none`` (it learns nothing).
        victim, victim_task, task, target: what was attacked, where and for what.
        epsilon, norm: the threat model.
        attack_success_rate, attack_success_ci, episodes: the final evaluation (success at any step).
        max_perturbation, mean_perturbation: over every step of the final evaluation.
        steps, labels: environment steps trained and labels used.
        train_minutes_this_session: wall-clock minutes of the call that finished the run.
        train_minutes: wall-clock minutes of training over every session of the run (a resumed run's
            earlier sessions included; 0 in older reports).
        clean_success_rate: the unattacked victim's success at the same target over the same
            episodes; an attack is worth only what it adds to this (``None`` in older reports).
        attacked_return, clean_return: the environment's own (task) return, mean over the final episodes, attacked
            and clean (``None`` in older reports).
        details: the method's own numbers.
    """

    method: str
    reward: str
    victim: str
    task: str
    target: str
    epsilon: float
    norm: str
    seed: int
    attack_success_rate: float
    attack_success_ci: list[float]
    episodes: int
    max_perturbation: float
    mean_perturbation: float
    steps: int = 0
    labels: int = 0
    victim_task: str | None = None
    train_minutes_this_session: float = 0.0
    train_minutes: float = 0.0
    clean_success_rate: float | None = None
    attacked_return: float | None = None
    clean_return: float | None = None
    details: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> str:
        lo, hi = self.attack_success_ci
        text = (f"attack success: {100 * self.attack_success_rate:.1f}% (95% CI {100 * lo:.1f}-{100 * hi:.1f}%, "
                f"{self.episodes} episodes), {self.labels} labels, {self.steps} steps; "
                f"max perturbation {self.max_perturbation:.4f} <= epsilon {self.epsilon:g} ({self.norm})")
        if (network := (self.details or {}).get("network_attack_success_rate")) is not None:
            text += f"; Δ refined at every observation (the adversary network's Δ alone: {100 * network:.1f}%"
            if (gap := self.details.get("refined_gap")) is not None:
                text += f"; gap left to π_θ's actions: {gap:.2f}"
            text += ")"
        if self.clean_success_rate is None:
            return text
        text += f"; the clean victim: {100 * self.clean_success_rate:.1f}%"
        if self.clean_success_rate >= 0.5 * max(self.attack_success_rate, 1e-9):
            text += (" -- the victim reaches this target on its own about as often, so this success says little "
                     "about the attack; choose a target it does not reach unattacked")
        return text


@dataclass
class IntentionReport(_Report):
    """The outcome of training an intention policy alone (``rat intention train``)."""

    task: str
    victim_task: str
    target: str
    steps: int
    queries_asked: int
    labels: int
    target_success_rate: float
    target_success_ci: list[float]
    final_eval_episodes: int
    preference_accuracy: float
    held_out_pairs: int
    reward_pearson: float
    quality_steps: int
    train_minutes_this_session: float = 0.0
    train_minutes: float = 0.0  #: over every session of the run (a resumed run's earlier ones included)
    details: dict[str, Any] = field(default_factory=dict)
