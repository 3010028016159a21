"""RAT's networks and losses (the paper's §4.2 and appendix B), as pure functions of parameters.

- the adversary π_α: a tanh-squashed Gaussian over Δ ∈ (−1, 1)^d;
- the weighting network h_ω: d → 64 → 64 → 1, ``1 + tanh``, so weights lie in (0, 2);
- the inner loss L(α; ω, θ) = E_s[h_ω(s) · KL(π_{ν∘α}(·|s) ‖ π_θ(·|s))];
- the outer loss J(α) = E_s[μ log π_{ν∘α}(a|s) − Q_φ(s, a)], a = the perturbed victim's action;
- the hypergradient ∇_ω J(α − η ∇_α L(α; ω)), exactly (per state) or in the released batch-mean form.

The perturbed policy is π_{ν∘α}(·|s) = N(μ_ν(s̃), σ_v² I) with σ_v = 1 (the victim is
deterministic; σ_v as released). The intention policy's distribution, for the KL, is the
Gaussian N(tanh μ_θ(s), σ_θ(s)² I): its mean action with its (pre-squash) standard deviation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn
from torch.func import functional_call

from rat.agents.networks import TanhGaussianActor, TwinCritic, mlp
from rat.attacks.threat import ThreatModel
from rat.victims.base import Victim


class Adversary(nn.Module):
    """π_α: Δ = tanh(μ(s) + σ(s)·ξ), ξ ~ N(0, I) (ξ = 0 gives the deterministic Δ)."""

    def __init__(self, obs_dim: int, hidden: int = 256, layers: int = 3):
        super().__init__()
        self.policy = TanhGaussianActor(obs_dim, obs_dim, hidden, layers)
        self.obs_dim = obs_dim

    def forward(self, obs: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        mu, log_std = self.policy.distribution_params(obs)
        if noise is None:
            return torch.tanh(mu)
        return torch.tanh(mu + log_std.exp() * noise)


@torch.no_grad()
def saturation(adversary: Adversary, obs: torch.Tensor) -> float:
    """The fraction of Δ's components at the ball's edge (|Δ_i| > 0.99), where tanh passes almost no gradient.

    Near 1, the adversary is stuck at corners of the ball: its inner loss can no longer move it.
    """
    return (adversary(obs).abs() > 0.99).float().mean().item()


class WeightingNetwork(nn.Module):
    """h_ω(s) ∈ (0, 2): an MLP d → 64 → 64 → 1 with ``1 + tanh`` output."""

    def __init__(self, obs_dim: int, hidden: int = 64):
        super().__init__()
        self.net = mlp(obs_dim, 1, hidden, layers=2)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return 1.0 + torch.tanh(self.net(obs).squeeze(-1))


def gaussian_kl(mean1: torch.Tensor, std1: float, mean2: torch.Tensor, log_std2: torch.Tensor,
                form: str = "exact") -> torch.Tensor:
    """KL(N(mean1, std1²) ‖ N(mean2, exp(log_std2)²)) of diagonal Gaussians, summed over the last axis.

    ``form="released"`` reproduces the released helper, which divides the squared mean gap by
    σ₂ instead of σ₂².
    """
    var2 = torch.exp(2.0 * log_std2)
    gap = (mean1 - mean2) ** 2
    gap_term = gap / (2.0 * var2) if form == "exact" else gap / (2.0 * var2.sqrt())
    return (log_std2 - math.log(std1) + std1**2 / (2.0 * var2) + gap_term - 0.5).sum(-1)


def intention_gaussian(intention: TanhGaussianActor, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The intention policy's mean action and log-std (no gradient: the adversary does not train it)."""
    with torch.no_grad():
        mu, log_std = intention.distribution_params(obs)
    return torch.tanh(mu), log_std


@dataclass(frozen=True)
class Imitation:
    """What the adversary is trained against: the frozen victim, the intention policy π_θ with its
    critic Q_φ and temperature μ, and the budget.

    Every method takes the adversary and, optionally, ``params`` that override its parameters
    (the virtual step of the hypergradient differentiates through them), and a batch of states:
    observations and, for a sequence victim, the context it had at each (else None).

    Attributes:
        victim: the frozen victim; gradients flow through it to the observation only.
        intention: π_θ's actor; critic, temperature: its Q_φ and μ.
        threat: the budget.
        victim_std: σ_v of the perturbed policy N(μ_ν(s̃), σ_v² I).
        kl_form: ``"exact"`` Gaussian KL or ``"released"`` (see :func:`gaussian_kl`).
    """

    victim: Victim
    intention: TanhGaussianActor
    critic: TwinCritic
    temperature: torch.Tensor
    threat: ThreatModel
    victim_std: float = 1.0
    kl_form: str = "exact"

    def perturbed_action(self, adversary: Adversary, params: dict | None, obs: torch.Tensor,
                         noise: torch.Tensor | None, context: Any = None) -> torch.Tensor:
        """μ_ν(s + ε·P(Δ_α(s))), differentiable in the adversary's parameters."""
        delta = adversary(obs, noise) if params is None else functional_call(adversary, params, (obs, noise))
        attacked = self.threat.perturb(obs, delta)
        return self.victim.act(attacked) if context is None else self.victim.act(attacked, context)

    @torch.no_grad()
    def gap(self, adversary: Adversary, obs: torch.Tensor, context: Any = None) -> float:
        """The imitation gap: mean ‖μ_ν(s̃) − tanh μ_θ(s)‖₂ over ``obs`` with the adversary's deterministic Δ."""
        target_mean, _ = intention_gaussian(self.intention, obs)
        return (self.perturbed_action(adversary, None, obs, None, context) - target_mean).norm(dim=-1).mean().item()

    def kl(self, adversary: Adversary, params: dict | None, obs: torch.Tensor, noise: torch.Tensor | None,
           context: Any = None) -> torch.Tensor:
        """KL(π_{ν∘α}(·|s) ‖ π_θ(·|s)) for each state of the batch, ``[B]``."""
        target_mean, target_log_std = intention_gaussian(self.intention, obs)
        action = self.perturbed_action(adversary, params, obs, noise, context)
        return gaussian_kl(action, self.victim_std, target_mean, target_log_std, self.kl_form)

    def outer(self, adversary: Adversary, params: dict | None, obs: torch.Tensor, noise: torch.Tensor | None,
              context: Any = None) -> torch.Tensor:
        """J(α) = mean_s[μ log π_{ν∘α}(a|s) − min Q_φ(s, a)], a = μ_ν(s̃).

        At a = the perturbed policy's mean, log π is the constant −(|A|/2) log(2π σ_v²); it is kept
        so the value is the paper's J, though only −Q carries a gradient.
        """
        action = self.perturbed_action(adversary, params, obs, noise, context)
        log_prob = -0.5 * action.shape[-1] * math.log(2 * math.pi * self.victim_std**2)
        q1, q2 = self.critic(obs, action)
        return (self.temperature.detach() * log_prob - torch.min(q1, q2)).mean()


def inner_loss(weights: torch.Tensor, kl: torch.Tensor) -> torch.Tensor:
    """L(α; ω, θ) = mean_s h_ω(s) · KL_s."""
    return (weights * kl).mean()


def hypergradient(objective: Imitation, adversary: Adversary, weighting: WeightingNetwork, obs_inner: torch.Tensor,
                  noise_inner: torch.Tensor, obs_outer: torch.Tensor, noise_outer: torch.Tensor, inner_lr: float,
                  form: str = "exact", context_inner: Any = None, context_outer: Any = None) -> list[torch.Tensor]:
    """∇_ω J(α'(ω)), α'(ω) = α − η ∇_α L(α; ω), one gradient per weighting-network parameter.

    ``form="exact"`` differentiates through the virtual step (per state: the paper's
    Σ_s f(s) ∇_ω h(s)); ``form="batch-mean"`` is the released approximation, which uses one
    scalar f̄ = −η (∇_α' J)ᵀ ∇_α mean_s KL_s for all states: ∇_ω ≈ f̄ ∇_ω mean_s h(s).
    """
    a_params = {k: v.detach().requires_grad_(True) for k, v in adversary.named_parameters()}
    w_params = dict(weighting.named_parameters())
    kl = objective.kl(adversary, a_params, obs_inner, noise_inner, context_inner)
    if form == "exact":
        weights = functional_call(weighting, w_params, (obs_inner,))
        grads = torch.autograd.grad(inner_loss(weights, kl), list(a_params.values()), create_graph=True)
        virtual = {k: p - inner_lr * g for (k, p), g in zip(a_params.items(), grads)}
        j = objective.outer(adversary, virtual, obs_outer, noise_outer, context_outer)
        return list(torch.autograd.grad(j, list(w_params.values()), allow_unused=True))
    if form != "batch-mean":
        raise ValueError(f"no hypergradient form '{form}'")
    with torch.no_grad():
        weights = weighting(obs_inner)
    grads = torch.autograd.grad(inner_loss(weights, kl), list(a_params.values()), retain_graph=True)
    virtual = {k: (p - inner_lr * g).detach().requires_grad_(True) for (k, p), g in zip(a_params.items(), grads)}
    j = objective.outer(adversary, virtual, obs_outer, noise_outer, context_outer)
    g_outer = torch.autograd.grad(j, list(virtual.values()))
    g_kl = torch.autograd.grad(kl.mean(), list(a_params.values()))
    f_bar = -inner_lr * sum((a * b).sum() for a, b in zip(g_outer, g_kl))
    mean_h = functional_call(weighting, w_params, (obs_inner,)).mean()
    return [f_bar * g for g in torch.autograd.grad(mean_h, list(w_params.values()))]
