"""Gradient attacks through the victim: the PA-AD actor and MAD.

Both search the ε-ball of the threat model (:class:`rat.attacks.threat.ThreatModel`) for the
observation that changes the victim's deterministic action the most in a given sense:

- :func:`directed_perturbation` (PA-AD's "actor", Sun et al. 2022): maximise
  ``cos(μ(s̃) − μ(s), d) + λ‖μ(s̃) − μ(s)‖`` for a direction ``d`` in the victim's action space;
- :func:`mad_perturbation` (maximal action difference): maximise ``‖μ(s̃) − μ(s)‖²``.

The search is one FGSM step from a random start in the ball (the paper's), or ``steps`` steps
of projected gradient ascent (PGD). Steps are taken in the geometry of the norm: the sign of the
gradient for ℓ∞, its direction for ℓ2, its largest coordinate for ℓ1, each followed by the
projection, so the result is always inside the ball.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from rat.attacks.threat import ThreatModel, project, random_delta
from rat.victims.base import Victim

Objective = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]  # (μ(s̃), μ(s)) -> per-state value [B]


def _ascent_direction(grad: torch.Tensor, norm: str) -> torch.Tensor:
    """The steepest-ascent step of unit size in ``norm`` for a gradient ``[B, d]``."""
    if norm == "linf":
        return grad.sign()
    if norm == "l2":
        return grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    index = grad.abs().argmax(-1, keepdim=True)  # ℓ1: all of the step on the steepest coordinate
    return torch.zeros_like(grad).scatter(-1, index, grad.gather(-1, index).sign())


def search_ball(victim: Victim, obs: torch.Tensor, objective: Objective, threat: ThreatModel, steps: int = 1, step_size: float | None = None, generator: np.random.Generator | None = None,
                context=None) -> torch.Tensor:
    """Δ in the unit ball (so s̃ = s + ε·Δ) that ascends ``objective`` from a random start.

    Args:
        victim: the frozen victim; gradients flow through it to the observation only.
        obs: true observations ``[B, d]``.
        objective: per-state value to maximise, from the attacked and the clean actions.
        steps: 1 is FGSM from a random start; more is PGD.
        step_size: in units of the ball's radius; default 1 for FGSM and 2.5/steps for PGD.
    """
    rng = generator if generator is not None else np.random.default_rng()
    obs = obs.float()
    norm = threat.norm
    start = np.stack([random_delta(rng, obs.shape[-1], norm) for _ in range(obs.shape[0])])
    delta = torch.as_tensor(start, dtype=obs.dtype)
    size = step_size if step_size is not None else (1.0 if steps == 1 else 2.5 / steps)
    with torch.no_grad():
        clean = victim.act(obs, context)
    for _ in range(steps):
        delta.requires_grad_(True)
        value = objective(victim.act(threat.perturb(obs, delta), context), clean).sum()
        (grad,) = torch.autograd.grad(value, delta)
        with torch.no_grad():
            delta = project(delta + size * _ascent_direction(grad, norm), norm)
    return delta.detach()


def directed_objective(direction: torch.Tensor, lam: float = 1.0) -> Objective:
    """PA-AD's actor objective cos(μ(s̃) − μ(s), d) + λ‖μ(s̃) − μ(s)‖ for directions ``d [B, |A|]``."""

    def value(attacked: torch.Tensor, clean: torch.Tensor) -> torch.Tensor:
        change = attacked - clean
        cosine = torch.nn.functional.cosine_similarity(change, direction.to(change), dim=-1, eps=1e-8)
        return cosine + lam * change.norm(dim=-1)

    return value


def mad_objective(attacked: torch.Tensor, clean: torch.Tensor) -> torch.Tensor:
    """MAD: the squared change of the victim's action."""
    return (attacked - clean).pow(2).sum(-1)


def directed_perturbation(victim: Victim, obs: torch.Tensor, direction: torch.Tensor, threat: ThreatModel,
                          lam: float = 1.0, steps: int = 1,
                          generator: np.random.Generator | None = None, context=None) -> torch.Tensor:
    """PA-AD's actor: Δ that moves the victim's action along ``direction`` (see module docstring)."""
    return search_ball(victim, obs, directed_objective(direction, lam), threat, steps,
                       generator=generator, context=context)


def mad_perturbation(victim: Victim, obs: torch.Tensor, threat: ThreatModel, steps: int = 10,
                     generator: np.random.Generator | None = None, context=None) -> torch.Tensor:
    """MAD: Δ that changes the victim's action the most (PGD, 10 steps by default)."""
    return search_ball(victim, obs, mad_objective, threat, steps, generator=generator, context=context)
