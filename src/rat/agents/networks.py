"""The small networks every part of RAT shares: an MLP, a tanh-Gaussian actor, a twin critic."""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F


def mlp(in_dim: int, out_dim: int, hidden: int = 256, layers: int = 3, activation: type[nn.Module] = nn.ReLU) -> nn.Sequential:
    """``layers`` hidden layers of width ``hidden``, then a linear output."""
    modules: list[nn.Module] = []
    width = in_dim
    for _ in range(layers):
        modules += [nn.Linear(width, hidden), activation()]
        width = hidden
    modules.append(nn.Linear(width, out_dim))
    return nn.Sequential(*modules)


class TanhGaussianActor(nn.Module):
    """A Gaussian policy squashed by tanh into the box ``[-1, 1]^act_dim``.

    ``forward(obs)`` is the deterministic (mean) action, differentiable in ``obs``: this is
    what victims and behaviour cloning use. ``sample(obs)`` draws a reparameterised action with
    its log-probability (SAC).
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden: int = 256, layers: int = 3,
                 log_std_bounds: tuple[float, float] = (-5.0, 2.0)):
        super().__init__()
        self.trunk = mlp(obs_dim, 2 * act_dim, hidden, layers)
        self.log_std_bounds = log_std_bounds
        self.obs_dim, self.act_dim = obs_dim, act_dim

    @classmethod
    def from_state_dict(cls, weights: dict[str, torch.Tensor]) -> "TanhGaussianActor":
        """An actor of the shape ``weights`` have (as :meth:`state_dict` gave them), loaded with them."""
        linear = sorted((k for k in weights if k.endswith(".weight")), key=lambda k: int(k.split(".")[1]))
        first, last = weights[linear[0]], weights[linear[-1]]
        actor = cls(first.shape[1], last.shape[0] // 2, first.shape[0], len(linear) - 1)
        actor.load_state_dict(weights)
        return actor

    def distribution_params(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pre-tanh mean and log-std, shape ``[B, act_dim]`` each."""
        mu, log_std = self.trunk(obs).chunk(2, dim=-1)
        lo, hi = self.log_std_bounds
        log_std = lo + 0.5 * (hi - lo) * (torch.tanh(log_std) + 1.0)
        return mu, log_std

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        mu, _ = self.distribution_params(obs)
        return torch.tanh(mu)

    def sample(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A reparameterised action ``[B, act_dim]`` and its log-probability ``[B]``."""
        mu, log_std = self.distribution_params(obs)
        std = log_std.exp()
        pre = mu + std * torch.randn_like(mu)
        action = torch.tanh(pre)
        log_prob = (-0.5 * ((pre - mu) / std) ** 2 - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)
        # log|d tanh(u)/du| = 2 (log 2 - u - softplus(-2u)), the numerically stable form.
        log_prob = log_prob - (2.0 * (math.log(2.0) - pre - F.softplus(-2.0 * pre))).sum(-1)
        return action, log_prob


class TwinCritic(nn.Module):
    """Two independent Q-functions ``Q(s, a)``; returns both, shape ``[B]`` each."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: int = 256, layers: int = 3):
        super().__init__()
        self.q1 = mlp(obs_dim + act_dim, 1, hidden, layers)
        self.q2 = mlp(obs_dim + act_dim, 1, hidden, layers)

    @classmethod
    def from_state_dict(cls, weights: dict[str, torch.Tensor], obs_dim: int) -> "TwinCritic":
        """A critic of the shape ``weights`` have (as :meth:`state_dict` gave them), loaded with them."""
        linear = sorted((k for k in weights if k.startswith("q1.") and k.endswith(".weight")),
                        key=lambda k: int(k.split(".")[1]))
        first = weights[linear[0]]
        critic = cls(obs_dim, first.shape[1] - obs_dim, first.shape[0], len(linear) - 1)
        critic.load_state_dict(weights)
        return critic

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([obs, action], dim=-1)
        return self.q1(x).squeeze(-1), self.q2(x).squeeze(-1)
