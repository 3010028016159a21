"""The victim: a frozen policy whose observations the adversary perturbs.

Every victim, whatever made it, is seen through one protocol, :class:`Victim`: a
differentiable deterministic action for a batch of observations, the spaces it expects, and an
optional sequence context for victims that read their history (Decision Transformers).
Victims are frozen when made: their parameters never require gradients and never change
during an attack, but gradients flow *through* them to the perturbed observation.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from rat.errors import RatError


@runtime_checkable
class Victim(Protocol):
    """What the attack needs of a victim.

    Attributes:
        observation_space: the observations it was trained on (a ``Box``).
        action_space: the actions it emits (a ``Box``).
        name: where it came from, for reports.
        meta: what is known of it (JSON-able): ``task`` where it records one, its provenance.
    """

    observation_space: gym.spaces.Box
    action_space: gym.spaces.Box
    name: str
    meta: dict[str, Any]

    def act(self, obs: torch.Tensor, context: Any = None) -> torch.Tensor:
        """Deterministic actions ``[B, act_dim]`` for observations ``[B, obs_dim]``, differentiable in ``obs``.

        ``context`` is whatever :meth:`initial_context` / :meth:`update_context` returned;
        memoryless victims ignore it.
        """

    def initial_context(self, batch_size: int = 1) -> Any:
        """The context at the start of an episode (``None`` for memoryless victims)."""

    def update_context(self, context: Any, obs: torch.Tensor, action: torch.Tensor, reward: torch.Tensor) -> Any:
        """The context after the victim saw ``obs``, emitted ``action`` and received ``reward``."""


class SequenceVictim(Victim, Protocol):
    """A victim that reads its history, and whose contexts pack into rows of floats.

    Training an attack draws states from many episodes and steps; each needs the context the
    victim had there, so the attack stores one packed row per state and unpacks a batch of them.
    """

    context_size: int  #: floats in one packed context

    def pack_context(self, context: Any) -> torch.Tensor:
        """``[B, context_size]``: one row per episode of ``context``."""

    def unpack_context(self, packed: torch.Tensor) -> Any:
        """The batch of contexts whose rows :meth:`pack_context` made."""

    # Optional: ``prepare(context)``, the same context made ready to act on many observations (its past
    # computed once); ``act`` in it gives the same actions. Attacks that act many times in one context use it.


def prepared(victim: Victim, context: Any) -> Any:
    """``context`` made ready for many observations where ``victim`` offers ``prepare``; else unchanged."""
    prepare = getattr(victim, "prepare", None)
    return context if prepare is None or context is None else prepare(context)


def is_sequence(victim: Victim) -> bool:
    """Whether ``victim`` reads its history (its episodes start from a context that is not None)."""
    return victim.initial_context(1) is not None


def require_memoryless(victim: Victim, method: str) -> None:
    """Raise a one-line error if ``method``, which perturbs without the victim's history, meets a sequence victim."""
    if is_sequence(victim):
        raise RatError(f"{method} computes perturbations without the victim's history, so it cannot attack the "
                       f"sequence victim '{victim.name}'; use rat, random or sa-rl")


def freeze(module: nn.Module) -> nn.Module:
    """Put ``module`` in eval mode and stop its parameters from ever requiring gradients."""
    module.eval()
    for p in module.parameters():
        p.requires_grad_(False)
    return module


class ModuleVictim(nn.Module):
    """A memoryless victim around a torch module mapping observations to actions.

    Args:
        policy: ``obs [B, obs_dim] -> action [B, act_dim]``, deterministic. It is frozen here.
        observation_space, action_space: what it expects and emits.
        name: a label for reports.
        squashed: the module outputs actions in ``[-1, 1]`` that are rescaled to the action
            space's bounds (SB3 and this project's actors do this); otherwise they are clipped.
        meta: what is known of it (``task``, provenance); see :attr:`Victim.meta`.
    """

    def __init__(self, policy: nn.Module, observation_space: gym.spaces.Box, action_space: gym.spaces.Box,
                 name: str = "torch-module", squashed: bool = True, meta: dict[str, Any] | None = None):
        super().__init__()
        self.policy = freeze(policy)
        self.observation_space, self.action_space, self.name = observation_space, action_space, name
        self.meta = dict(meta or {})
        self.squashed = squashed
        self.register_buffer("low", torch.as_tensor(action_space.low, dtype=torch.float32))
        self.register_buffer("high", torch.as_tensor(action_space.high, dtype=torch.float32))

    def train(self, mode: bool = True) -> ModuleVictim:
        # A victim never leaves eval mode (dropout or batch-norm would make it stochastic).
        return super().train(False)

    def act(self, obs: torch.Tensor, context: Any = None) -> torch.Tensor:
        out = self.policy(obs.float())
        if self.squashed:
            return self.low + 0.5 * (out + 1.0) * (self.high - self.low)
        return torch.max(torch.min(out, self.high), self.low)

    forward = act

    def load_policy(self, state: dict[str, torch.Tensor]) -> None:
        """Replace the policy's weights in place, frozen as before: everything holding this victim (an attack's
        trainer, an adversary's MDP) acts on the new weights from now on (robust training swaps its agent in)."""
        self.policy.load_state_dict(state)
        freeze(self.policy)

    def initial_context(self, batch_size: int = 1) -> None:
        return None

    def update_context(self, context, obs, action, reward) -> None:
        return None


class VictimPolicy:
    """A victim as ``obs -> action`` in numpy, one observation at a time, for rollouts.

    A sequence victim's context is kept here: :meth:`reset` starts an episode, and
    :meth:`observe` records the step just taken (the observation as the victim saw it, its
    action, and the environment's reward). Memoryless victims need neither.
    """
    # The context always records what happened: when someone else acted for the victim (the combined
    # behaviour policy hands control to π_θ), ``observe(reward, seen, taken)`` records that step.

    def __init__(self, victim: Victim):
        self.victim = victim
        self.device = victim_device(victim)
        self.context = victim.initial_context(1)
        self._last: tuple[torch.Tensor, torch.Tensor] | None = None

    def reset(self) -> None:
        self.context, self._last = self.victim.initial_context(1), None

    @torch.no_grad()
    def __call__(self, obs: np.ndarray) -> np.ndarray:
        o = torch.as_tensor(obs, dtype=torch.float32, device=self.device).unsqueeze(0)
        action = self.victim.act(o, self.context)
        self._last = (o, action)
        return action.squeeze(0).cpu().numpy()

    def observe(self, reward: float, seen: np.ndarray | None = None, taken: np.ndarray | None = None) -> None:
        """Record the step just taken: by default what the victim saw and did at its last call; ``seen`` and
        ``taken`` when the action was someone else's, so the history stays the episode's own."""
        if self.context is None:
            return
        if seen is not None:
            as_row = lambda x: torch.as_tensor(x, dtype=torch.float32, device=self.device).reshape(1, -1)  # noqa: E731
            self._last = (as_row(seen), as_row(taken))
        if self._last is not None:
            obs, action = self._last
            self.context = self.victim.update_context(self.context, obs, action, torch.tensor([float(reward)]))
            self._last = None


def victim_device(victim: Victim) -> torch.device | str:
    """Where a victim's weights are (``"cpu"`` for one without any)."""
    return next(iter(victim.parameters()), torch.empty(0)).device if isinstance(victim, nn.Module) else "cpu"


def numpy_policy(victim: Victim) -> VictimPolicy:
    """``obs -> action`` in numpy for rollouts of a victim (see :class:`VictimPolicy`)."""
    return VictimPolicy(victim)


def check_compatible(victim: Victim, env: gym.Env, env_name: str = "the environment") -> None:
    """Raise a one-line :class:`RatError` saying exactly how ``victim`` and ``env`` disagree."""
    problems = []
    v_obs, e_obs = victim.observation_space, env.observation_space
    v_act, e_act = victim.action_space, env.action_space
    if tuple(v_obs.shape) != tuple(e_obs.shape):
        problems.append(f"observation shape {tuple(v_obs.shape)} vs {tuple(e_obs.shape)}")
    if tuple(v_act.shape) != tuple(e_act.shape):
        problems.append(f"action shape {tuple(v_act.shape)} vs {tuple(e_act.shape)}")
    elif not (np.allclose(v_act.low, e_act.low) and np.allclose(v_act.high, e_act.high)):
        problems.append(f"action bounds [{v_act.low.min():g}, {v_act.high.max():g}] vs "
                        f"[{e_act.low.min():g}, {e_act.high.max():g}]")
    if problems:
        raise RatError(f"victim '{victim.name}' does not fit {env_name} (victim vs env: {'; '.join(problems)}); "
                       "pick a victim trained on this task or the matching task")
