"""Soft Actor-Critic, compact: losses are pure functions, the update step owns the optimisers.

Defaults are the paper's table 7 (the SAC used for victims); the intention policy overrides
the learning rate (``docs/design.md`` §4).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from rat.agents.networks import PRECISIONS, TanhGaussianActor, TwinCritic, adam, keep_fused, mixed_precision
from rat.errors import RatError


@dataclass(frozen=True)
class SACConfig:
    """SAC hyperparameters (defaults: the paper's table 7)."""

    hidden: int = 256  #: width of every hidden layer
    layers: int = 3  #: hidden layers in actor and critics
    lr: float = 1e-4  #: Adam learning rate of actor and critics
    alpha_lr: float = 1e-4  #: Adam learning rate of the temperature
    init_temperature: float = 0.1  #: initial entropy temperature
    gamma: float = 0.99  #: discount
    tau: float = 0.005  #: target-critic EMA rate
    target_update_every: int = 2  #: critic target update period, in updates
    actor_update_every: int = 1  #: actor and temperature update period, in updates
    batch_size: int = 1024  #: transitions per update
    log_std_bounds: tuple[float, float] = (-5.0, 2.0)  #: actor log-std range
    learnable_temperature: bool = True  #: tune the temperature towards the target entropy
    #: arithmetic of the hidden layers in an update: "fp32", or "bf16" (autocast; output layers, weights,
    #: gradients and Adam stay float32; acting is float32 either way). What it costs and does: benchmarks/speed.md
    precision: str = "fp32"

    def __post_init__(self):
        if self.precision not in PRECISIONS:
            raise RatError(f"unknown SAC precision '{self.precision}'; use one of: {', '.join(PRECISIONS)}")


# --- losses: pure functions of networks and a batch ----------------------------------------------


def critic_loss(critic: TwinCritic, critic_target: TwinCritic, actor: TanhGaussianActor, alpha: torch.Tensor,
                batch: dict[str, torch.Tensor], gamma: float) -> dict[str, torch.Tensor]:
    """Soft Bellman residual of both critics; bootstraps unless ``terminated``."""
    with torch.no_grad():
        next_action, next_log_prob = actor.sample(batch["next_obs"])
        tq1, tq2 = critic_target(batch["next_obs"], next_action)
        target_v = torch.min(tq1, tq2) - alpha * next_log_prob
        target_q = batch["reward"] + gamma * (1.0 - batch["terminated"]) * target_v
    q1, q2 = critic(batch["obs"], batch["action"])
    loss = ((q1 - target_q) ** 2).mean() + ((q2 - target_q) ** 2).mean()
    return {"critic_loss": loss, "q_mean": q1.mean().detach(), "target_q_mean": target_q.mean()}


ActorTerm = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]  #: (obs, sampled action) -> a loss per row, [B]


def actor_loss(actor: TanhGaussianActor, critic: TwinCritic, alpha: torch.Tensor, obs: torch.Tensor,
               extra: ActorTerm | None = None) -> dict[str, torch.Tensor]:
    """``E[alpha log pi(a|s) - min Q(s, a) + extra(s, a)]``, a ~ pi (the paper's eq. for J_pi; ``extra`` is a
    robust-training term such as RAT-WocaR's, evaluated at the same reparameterised sample)."""
    action, log_prob = actor.sample(obs)
    q1, q2 = critic(obs, action)
    per_row = alpha.detach() * log_prob - torch.min(q1, q2)
    out = {"log_prob": log_prob.detach()}
    if extra is not None:
        term = extra(obs, action)
        per_row = per_row + term
        out["actor_extra"] = term.mean().detach()
    return {"actor_loss": per_row.mean(), **out}


def temperature_loss(log_alpha: torch.Tensor, log_prob: torch.Tensor, target_entropy: float) -> torch.Tensor:
    """Drives the policy's entropy towards ``target_entropy``."""
    return (log_alpha.exp() * (-log_prob - target_entropy)).mean()


# --- the agent -----------------------------------------------------------------------------------


class SAC(nn.Module):
    """Actor, twin critic, target critic and temperature, with their optimisers."""

    def __init__(self, obs_dim: int, act_dim: int, config: SACConfig = SACConfig(), device: str = "cpu"):
        super().__init__()
        self.config, self.obs_dim, self.act_dim = config, obs_dim, act_dim
        self.actor = TanhGaussianActor(obs_dim, act_dim, config.hidden, config.layers, config.log_std_bounds)
        self.critic = TwinCritic(obs_dim, act_dim, config.hidden, config.layers)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = nn.Parameter(torch.tensor(float(np.log(config.init_temperature))))
        self.target_entropy = -float(act_dim)
        self.to(device)
        self.device = device
        self.actor_opt = adam(self.actor.parameters(), config.lr)
        self.critic_opt = adam(self.critic.parameters(), config.lr)
        self.alpha_opt = adam([self.log_alpha], config.alpha_lr)
        self.updates = 0

    @property
    def alpha(self) -> torch.Tensor:
        return self.log_alpha.exp()

    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """Action for one observation (numpy in, numpy out)."""
        x = torch.as_tensor(obs, dtype=torch.float32, device=self.device).unsqueeze(0)
        action = self.actor(x) if deterministic else self.actor.sample(x)[0]
        return action.squeeze(0).cpu().numpy()

    def reset_critic(self) -> None:
        """Re-initialise critics and their optimiser (PEBBLE does this after the first query round)."""
        cfg = self.config
        self.critic = TwinCritic(self.obs_dim, self.act_dim, cfg.hidden, cfg.layers).to(self.device)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.critic_opt = adam(self.critic.parameters(), cfg.lr)

    def update(self, batch: dict[str, torch.Tensor], actor: bool = True, actor_extra: ActorTerm | None = None
               ) -> dict[str, float]:
        """One SAC update on ``batch``; returns its metrics. ``actor=False`` steps the critic alone (a critic
        warm-up for an actor loaded from elsewhere); ``actor_extra`` is added to the actor's loss per row."""
        cfg = self.config
        metrics: dict[str, float] = {}
        with mixed_precision(cfg.precision, self.device):
            out = critic_loss(self.critic, self.critic_target, self.actor, self.alpha.detach(), batch, cfg.gamma)
        self.critic_opt.zero_grad(set_to_none=True)
        out["critic_loss"].backward()
        self.critic_opt.step()
        metrics.update({k: v.item() for k, v in out.items()})

        if actor and self.updates % cfg.actor_update_every == 0:
            self.critic.requires_grad_(False)  # the actor loss must not move the critic
            with mixed_precision(cfg.precision, self.device):  # its own context: the critic was just stepped
                out = actor_loss(self.actor, self.critic, self.alpha, batch["obs"], actor_extra)
            self.critic.requires_grad_(True)
            self.actor_opt.zero_grad(set_to_none=True)
            out["actor_loss"].backward()
            self.actor_opt.step()
            metrics["actor_loss"] = out["actor_loss"].item()
            metrics["entropy"] = float(-out["log_prob"].mean())
            if "actor_extra" in out:
                metrics["actor_extra"] = out["actor_extra"].item()
            if cfg.learnable_temperature:
                loss = temperature_loss(self.log_alpha, out["log_prob"], self.target_entropy)
                self.alpha_opt.zero_grad(set_to_none=True)
                loss.backward()
                self.alpha_opt.step()
                metrics["alpha_loss"] = loss.item()
        if self.updates % cfg.target_update_every == 0:
            with torch.no_grad():
                torch._foreach_lerp_(list(self.critic_target.parameters()), list(self.critic.parameters()), cfg.tau)
        self.updates += 1
        metrics["alpha"] = self.alpha.item()
        return metrics

    # --- checkpoints -------------------------------------------------------------------------

    def optimizer_state(self) -> dict:
        return {"actor": self.actor_opt.state_dict(), "critic": self.critic_opt.state_dict(),
                "alpha": self.alpha_opt.state_dict(), "updates": self.updates}

    def load_optimizer_state(self, state: dict) -> None:
        self.actor_opt.load_state_dict(state["actor"])
        self.critic_opt.load_state_dict(state["critic"])
        self.alpha_opt.load_state_dict(state["alpha"])
        for optimizer in (self.actor_opt, self.critic_opt, self.alpha_opt):
            keep_fused(optimizer)
        self.updates = int(state["updates"])

    def describe(self) -> dict:
        """JSON-able description of the agent's shape and configuration."""
        return {"obs_dim": self.obs_dim, "act_dim": self.act_dim, "sac": asdict(self.config)}
