"""A worked plugin: a hand-made attack and a target behaviour of one's own, used from the command line.

    rat --plugin examples/my_attacks.py list attacks
    rat --plugin examples/my_attacks.py attack train --method blind-hand --target hold-high \
        --victim zoo:drawer-close-v3 --set final_eval_episodes=10 --out runs/blind-hand
    rat --plugin examples/my_attacks.py bench table1 --tasks drawer-close-v3 --scenarios hold-high \
        --methods blind-hand,random --seeds 0 --preset smoke --out runs/my-grid

- ``blind-hand`` learns nothing: it tells the victim its gripper is ε lower on every axis than it
  is (the first three observation entries are the gripper's position), at every step.
- ``hold-high`` wants the gripper above z = 0.30 m for 20 consecutive steps: a success test that
  needs the episode so far, so it is registered with ``stateful=True``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rat.attacks import AttackSetup, register_attack
from rat.attacks.runs import baseline_run
from rat.envs import register_target


@dataclass(frozen=True)
class BlindHandConfig:
    """Settings of the blind-hand attack."""

    final_eval_episodes: int = 30  #: episodes of the final evaluation
    dims: int = 3  #: observation entries pushed (the gripper's x, y, z)


@register_attack("blind-hand", config=BlindHandConfig, rewards=("none",))
class BlindHand:
    """Blind hand: the gripper is reported ε lower on every axis (a fixed, hand-made perturbation)."""

    def train(self, setup: AttackSetup, config: BlindHandConfig, out: Path):
        return baseline_run(self.name, setup, out, {"dims": config.dims}, final_episodes=config.final_eval_episodes)

    def load(self, run: Path, meta: dict, victim):
        delta = np.zeros(int(meta["obs_dim"]))
        delta[: int(meta["dims"])] = -1.0  # Δ; the threat model projects it into its ball and scales it by ε
        return lambda obs: delta


class HeldHigh:
    """One episode's success test: the gripper above 0.30 m for 20 consecutive steps."""

    def __init__(self):
        self.run = 0

    def __call__(self, info) -> bool:
        self.run = self.run + 1 if info["tcp_pos"][2] > 0.30 else 0
        return self.run >= 20


@register_target("hold-high", success=HeldHigh, stateful=True,
                 description="hold the gripper above z = 0.30 m for 20 consecutive steps")
def lift_gripper(obs, action, next_obs, info) -> float:
    """Ten times the gripper's rise during the step, plus 1 for every step spent above 0.30 m."""
    return 10.0 * float(info["tcp_pos"][2] - info["prev_tcp_pos"][2]) + float(info["tcp_pos"][2] > 0.30)
