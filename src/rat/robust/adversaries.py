"""The adversaries of robust training, each steppable between its agent's phases.

A robust-training loop needs three things of an attack it does not need elsewhere: to be advanced a
unit at a time and stopped at any phase end (:meth:`PhaseAdversary.advance`), to keep learning against a
victim whose weights change in place between its phases (:meth:`rat.victims.ModuleVictim.load_policy`),
and to hand the agent's phase a frozen ``obs -> Δ`` (:meth:`PhaseAdversary.perturbation`). Both kinds of
adversary the table-3 methods use are thin views of the attacks' own trainers:

- :class:`RATAdversary`: the whole RAT run (:class:`~rat.attacks.rat.RATTrainer`), one environment step
  at a time: its intention policy, r̂, label store and buffers carry over from phase to phase;
- :class:`PPOAdversary`: SA-RL's or PA-AD's PPO (:class:`~rat.attacks.rl.PPOTrainer`), one rollout and
  update at a time, the episode under way continued.
"""

from __future__ import annotations

from typing import Any, Protocol

import gymnasium as gym
import numpy as np
import torch

from rat.attacks.base import AttackSetup
from rat.attacks.rat import RATTrainer
from rat.attacks.rl import PPOTrainer
from rat.attacks.threat import Perturbation


class PhaseAdversary(Protocol):
    """What the robust trainer asks of an adversary. ``step`` counts the adversary's environment steps."""

    step: int

    def advance(self) -> dict[str, float] | None:
        """One unit of training against the victim as it is now; metrics at a safe point for a checkpoint."""

    def perturbation(self, sample: bool) -> Perturbation:
        """The adversary as it is, as ``obs -> Δ``: sampled (exploring, as ATLA's agent phase sees it) or its mean."""

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any], meta: dict[str, Any]) -> None: ...

    def checkpoint_meta(self) -> dict[str, Any]: ...


class RATAdversary:
    """RAT as a phase adversary: :class:`RATTrainer` advanced one environment step at a time."""

    def __init__(self, trainer: RATTrainer):
        self.trainer = trainer

    @property
    def step(self) -> int:
        return self.trainer.step

    def advance(self) -> dict[str, float] | None:
        return self.trainer.advance()

    def perturbation(self, sample: bool) -> Perturbation:
        adversary, device = self.trainer.adversary, self.trainer.device

        @torch.no_grad()
        def delta(obs: np.ndarray) -> np.ndarray:
            s = torch.as_tensor(obs, dtype=torch.float32, device=device).unsqueeze(0)
            return adversary(s, torch.randn_like(s) if sample else None).squeeze(0).double().cpu().numpy()

        return delta

    def state_dict(self) -> dict[str, Any]:
        return self.trainer.state_dict()

    def load_state_dict(self, state: dict[str, Any], meta: dict[str, Any]) -> None:
        self.trainer.load_state_dict(state, meta)

    def checkpoint_meta(self) -> dict[str, Any]:
        return self.trainer.checkpoint_meta()


class PPOAdversary:
    """SA-RL or PA-AD as a phase adversary: one PPO rollout and update per :meth:`advance`.

    The agent's phase sees the PPO policy's action (sampled or its mean) turned into Δ by the adversary's
    own MDP, exactly as in training: SA-RL's action is Δ, PA-AD's a direction its gradient actor follows.
    """

    def __init__(self, trainer: PPOTrainer, mdp: gym.Env):
        self.trainer, self.mdp = trainer, mdp

    @property
    def step(self) -> int:
        return self.trainer.step

    def advance(self) -> dict[str, float] | None:
        return {"adversary_rollout_steps": float(self.trainer.rollout())}

    def perturbation(self, sample: bool) -> Perturbation:
        policy, space = self.trainer.model.policy, self.mdp.action_space

        def delta(obs: np.ndarray) -> np.ndarray:
            action, _ = policy.predict(np.asarray(obs, np.float32), deterministic=not sample)
            action = np.clip(action, space.low, space.high)
            s = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
            return self.mdp.perturbation(s, action).squeeze(0).detach().double().numpy()

        return delta

    def state_dict(self) -> dict[str, Any]:
        return self.trainer.state_dict()

    def load_state_dict(self, state: dict[str, Any], meta: dict[str, Any]) -> None:
        self.trainer.load_state_dict(state, {"step": meta["adversary_step"]})
        self.trainer.model._last_obs = None  # the episode under way at the checkpoint is gone: PPO starts a new one

    def checkpoint_meta(self) -> dict[str, Any]:
        return {}


def ppo_adversary(method: str, setup: AttackSetup, env: gym.Env, reward, config) -> PPOAdversary:
    """SA-RL (``sa-rl``) or PA-AD (``pa-ad``) in ``env`` against ``setup.victim``, learning from ``reward``."""
    from rat.attacks.base import get_attack

    attack = get_attack(method)
    mdp = attack.mdp(env, setup, reward, config)
    return PPOAdversary(PPOTrainer(attack, setup, mdp, config), mdp)
