"""The white-box steerability probe: how far a greedy attacker who knows the goal can steer a victim in the ε-ball.

At every step it searches the ball for the observation that turns the victim's action most towards where the
target behaviour wants it: ``restarts`` random starts × ``steps`` steps of projected gradient ascent on the
goal-ward component of the victim's action, keeping the best start. Nothing is learnt; it needs the victim's
gradients and a *steering* for the target (observation -> the wanted direction in action space), so it is an
upper reference for what the victim's sensitivity allows, not an attack an outsider could mount.

Targets with a steering: ``reach`` (the gripper towards its point). Register one for your own target with
:func:`register_steering`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from rat.attacks.base import AttackSetup, register_attack
from rat.attacks.gradient import search_ball
from rat.attacks.runs import baseline_run
from rat.attacks.threat import Perturbation, ThreatModel
from rat.errors import RatError
from rat.reports import AttackReport
from rat.victims.base import Victim

Steering = Callable[[np.ndarray], np.ndarray]  #: true observation -> the wanted direction in the victim's action space
_STEERING: dict[str, Steering] = {}


def register_steering(target: str, direction: Steering) -> Steering:
    """Give the probe a direction for ``target`` (a registered target behaviour's name)."""
    _STEERING[target] = direction
    return direction


def steering_for(target: str) -> Steering:
    if target not in _STEERING:
        raise RatError(f"the probe needs to know which way target '{target}' lies; targets it can steer to: "
                       f"{', '.join(sorted(_STEERING))} (add one with rat.attacks.probe.register_steering)")
    return _STEERING[target]


def _reach(obs: np.ndarray) -> np.ndarray:
    from rat.envs.targets import REACH_GOAL

    direction = np.zeros(4)
    direction[:3] = REACH_GOAL - obs[:3]  # Meta-World's observation starts with the gripper's position
    return direction


register_steering("reach", _reach)


def greedy_delta(victim: Victim, obs: np.ndarray, direction: np.ndarray, threat: ThreatModel, restarts: int,
                 steps: int, rng: np.random.Generator) -> torch.Tensor:
    """Δ in the unit ball maximising the component of the victim's action along ``direction`` (best of ``restarts``)."""
    s = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0).repeat(restarts, 1)
    d = torch.as_tensor(direction, dtype=torch.float32)
    d = d / d.norm().clamp_min(1e-9)

    def goalward(attacked: torch.Tensor, clean: torch.Tensor) -> torch.Tensor:
        return attacked @ d

    delta = search_ball(victim, s, goalward, threat, steps, generator=rng)
    with torch.no_grad():
        values = goalward(victim.act(threat.perturb(s, delta)), None)
    return delta[values.argmax()]


def probe_perturbation(victim: Victim, steering: Steering, threat: ThreatModel, restarts: int, steps: int,
                       seed: int) -> Perturbation:
    """The probe as ``obs -> Δ``."""
    rng = np.random.default_rng(seed)

    def delta(obs: np.ndarray) -> np.ndarray:
        return greedy_delta(victim, obs, steering(obs), threat, restarts, steps, rng).double().numpy()

    return delta


@dataclass(frozen=True)
class ProbeConfig:
    """Settings of the probe (it learns nothing)."""

    restarts: int = 16  #: random starts in the ball per observation
    steps: int = 30  #: projected-gradient steps from each
    final_eval_episodes: int = 30  #: episodes of the final evaluation

    def __post_init__(self):
        for name in ("restarts", "steps", "final_eval_episodes"):
            if getattr(self, name) <= 0:
                raise RatError(f"{name.replace('_', '-')} must be positive, got {getattr(self, name)}")


@register_attack("probe", config=ProbeConfig, rewards=("none",))
class Probe:
    """The white-box steerability probe: greedy, knows the goal (a reference, not an outsider's attack)."""

    def train(self, setup: AttackSetup, config: ProbeConfig, out: Path) -> AttackReport:
        steering_for(setup.target.name)  # said before anything is written
        return baseline_run("probe", setup, out, {"restarts": config.restarts, "steps": config.steps},
                            final_episodes=config.final_eval_episodes)

    def load(self, run: Path, meta: dict, victim: Victim) -> Perturbation:
        threat = ThreatModel(float(meta["epsilon"]), meta["norm"])
        return probe_perturbation(victim, steering_for(meta["target"]), threat, int(meta["restarts"]),
                                  int(meta["steps"]), int(meta["seed"]))
