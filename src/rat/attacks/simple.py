"""Attacks that learn nothing: random (the paper's baseline) and MAD (maximal action difference).

- ``random``: Δ uniform in the ε-ball, a new draw every step.
- ``mad``: the perturbation that changes the victim's action the most (PGD through the victim),
  untargeted; the robustness literature's standard attack, for the robust-training tables.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rat.attacks.base import AttackSetup, register_attack
from rat.attacks.gradient import mad_perturbation
from rat.attacks.runs import baseline_run
from rat.attacks.threat import Perturbation, ThreatModel
from rat.errors import RatError
from rat.reports import AttackReport
from rat.victims.base import Victim, require_memoryless


@dataclass(frozen=True)
class SimpleConfig:
    """Settings of an attack that learns nothing."""

    final_eval_episodes: int = 30  #: episodes of the final evaluation (the paper's 30)
    pgd_steps: int = 10  #: MAD's projected-gradient steps

    def __post_init__(self):
        for name in ("final_eval_episodes", "pgd_steps"):
            if getattr(self, name) <= 0:
                raise RatError(f"{name.replace('_', '-')} must be positive, got {getattr(self, name)}")


def _threat(meta: dict) -> ThreatModel:
    return ThreatModel(float(meta["epsilon"]), meta["norm"])


def random_perturbation(dim: int, threat: ThreatModel, seed: int) -> Perturbation:
    rng = np.random.default_rng(seed)
    return lambda obs: threat.random_delta(rng, dim)


def mad_attack(victim: Victim, threat: ThreatModel, seed: int, steps: int = 10) -> Perturbation:
    require_memoryless(victim, "mad")
    rng = np.random.default_rng(seed)

    def delta(obs: np.ndarray) -> np.ndarray:
        s = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
        return mad_perturbation(victim, s, threat, steps, rng).squeeze(0).double().numpy()

    return delta


@register_attack("random", config=SimpleConfig)
class RandomAttack:
    """Random: Δ uniform in the ε-ball (no training)."""

    def train(self, setup: AttackSetup, config: SimpleConfig, out: Path) -> AttackReport:
        return baseline_run("random", setup, out, {}, final_episodes=config.final_eval_episodes)

    def load(self, run: Path, meta: dict, victim: Victim) -> Perturbation:
        return random_perturbation(int(meta["obs_dim"]), _threat(meta), int(meta["seed"]))


@register_attack("mad", config=SimpleConfig)
class MADAttack:
    """MAD: the perturbation that changes the victim's action the most (untargeted, PGD)."""

    def train(self, setup: AttackSetup, config: SimpleConfig, out: Path) -> AttackReport:
        return baseline_run("mad", setup, out, {"pgd_steps": config.pgd_steps},
                            final_episodes=config.final_eval_episodes)

    def load(self, run: Path, meta: dict, victim: Victim) -> Perturbation:
        return mad_attack(victim, _threat(meta), int(meta["seed"]), int(meta.get("pgd_steps", 10)))
