"""The small networks every part of RAT shares: an MLP, a tanh-Gaussian actor, a twin critic."""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from rat.errors import RatError

PRECISIONS = ("fp32", "bf16")  #: arithmetic of the networks' hidden layers in an update (:func:`mixed_precision`)


class MLP(nn.Sequential):
    """Linear and activation layers in order, as :class:`nn.Sequential` (the same parameters and state-dict
    keys); under :func:`mixed_precision` the hidden layers run in bfloat16 and the output layer in float32,
    so Q-values, rewards and log-std keep float32's resolution (a bf16 Q of 100 is only good to ±0.4)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        *hidden, out = self
        for layer in hidden:
            x = layer(x)
        if not torch.is_autocast_enabled(x.device.type):
            return out(x)
        with torch.autocast(x.device.type, enabled=False):
            return out(x.float())


def mlp(in_dim: int, out_dim: int, hidden: int = 256, layers: int = 3, activation: type[nn.Module] = nn.ReLU) -> MLP:
    """``layers`` hidden layers of width ``hidden``, then a linear output."""
    modules: list[nn.Module] = []
    width = in_dim
    for _ in range(layers):
        modules += [nn.Linear(width, hidden), activation()]
        width = hidden
    modules.append(nn.Linear(width, out_dim))
    return MLP(*modules)


def mixed_precision(precision: str, device: str | torch.device = "cpu"):
    """The context a loss is computed in: ``"bf16"`` autocasts matrix products to bfloat16 (master weights,
    gradients and optimiser states stay float32; no loss scaling, bfloat16 has float32's range), ``"fp32"``
    changes nothing. Use one context per loss whose networks were just stepped: autocast caches each
    weight's bfloat16 copy for the whole context, so a second loss inside it would see the weights before
    the step."""
    if precision not in PRECISIONS:
        raise RatError(f"unknown precision '{precision}'; use one of: {', '.join(PRECISIONS)}")
    return torch.autocast(torch.device(device).type, dtype=torch.bfloat16, enabled=precision == "bf16")


def adam(params, lr: float) -> torch.optim.Adam:
    """Adam with torch's fused kernel where the parameters' device has one (the same update, one kernel for
    all parameters instead of several per tensor: ``benchmarks/speed.md``)."""
    params = list(params)
    fused = bool(params) and all(p.device.type in ("cpu", "cuda") and p.is_floating_point() for p in params)
    return torch.optim.Adam(params, lr=lr, fused=fused or None)


def keep_fused(optimizer: torch.optim.Optimizer) -> None:
    """After ``load_state_dict``: the saved param groups' ``fused``/``foreach`` flags replace the optimiser's
    own, so a checkpoint written without the fused kernel would resume without it; restore the optimiser's."""
    for group in optimizer.param_groups:
        group["fused"], group["foreach"] = optimizer.defaults.get("fused"), optimizer.defaults.get("foreach")


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
    def from_state_dict(cls, weights: dict[str, torch.Tensor]) -> TanhGaussianActor:
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
    def from_state_dict(cls, weights: dict[str, torch.Tensor], obs_dim: int) -> TwinCritic:
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
