"""Terms a robust agent adds to SAC's actor loss, per row, at the actor's reparameterised sample ã.

- :class:`IntentionValue` — RAT-WocaR as the RAT release writes it: κ·min(Q_φ^targ₁, Q_φ^targ₂)(s, ã), with
  Q_φ the *intention policy's* target twin critic (the attacker's value of the target behaviour): the agent
  is pushed away from actions that serve the attacker's target.
- :class:`WorstCaseValue` — WocaR's own idea made exact for this threat model: a worst-attack Q_w of the task
  reward, learnt with the Bellman operator Q_w(s, a) ← r + γ(1 − d)·Q̄_w(s′, a_w′), where a_w′ is the agent's
  action at the observation in the ε-ball around s′ that minimises Q̄_w (found by projected signed-gradient
  steps on the perturbation, in place of WocaR's interval bounds on the action); the term is −κ·Q_w(s, ã).
- :func:`state_smoothness` — SA-PPO's state regulariser in SAC form (PA-ATLA's agent uses it): λ·‖μ(s̃*) −
  μ(s)‖², s̃* the observation in the ball that moves the actor's mean action most.
- :class:`Anchor` — λ·|Q̄|·‖ã − μ₀(s)‖², μ₀ the actor the agent started from (TD3+BC's behaviour term and
  its Q scale), ã drawn at the perturbed observation s̃ and μ₀ taken at the true one s: fine-tuning stays near
  the actor whose value the critic has learnt, and near what that actor does when nothing is perturbed.

κ may ramp from 0 (WocaR's schedule) or stay constant (the release's).
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import torch
from torch import nn

from rat.agents.networks import TanhGaussianActor, TwinCritic, adam, mlp
from rat.attacks.threat import ThreatModel


def kappa_at(kappa: float, schedule: str, progress: float) -> float:
    """κ at ``progress`` ∈ [0, 1] of the agent's training: constant, or linear from 0 (WocaR's)."""
    return kappa if schedule == "constant" else kappa * min(max(progress, 0.0), 1.0)


def worst_observation(actor: TanhGaussianActor, value: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                      obs: torch.Tensor, threat: ThreatModel, steps: int, sign: float = -1.0) -> torch.Tensor:
    """The observation in the ε-ball around each row of ``obs`` at which ``value(obs, μ(s̃))`` is least
    (``sign=-1``) or greatest (``sign=+1``): ``steps`` signed-gradient steps on Δ from 0, each projected back.
    Only Δ is differentiated: no parameter's gradient is touched."""
    delta = torch.zeros_like(obs, requires_grad=True)
    size = 2.0 / max(steps, 1)  # the ball's whole width over the steps (Δ lives in the unit ball)
    for _ in range(steps):
        loss = value(obs, actor(threat.perturb(obs, delta))).sum()
        grad, = torch.autograd.grad(loss, delta)
        with torch.no_grad():
            delta += sign * size * grad.sign()
            delta.copy_(threat.project(delta))
    return threat.perturb(obs, delta.detach()).detach()


class IntentionValue:
    """κ·min Q_φ^targ(s, ã): the released RAT-WocaR term, from a frozen copy of the intention policy's target critic."""

    def __init__(self, critic_target: TwinCritic):
        self.critic = copy.deepcopy(critic_target).requires_grad_(False)
        self.kappa = 0.0

    def __call__(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.kappa * torch.min(*self.critic(obs, action))

    def state_dict(self) -> dict:
        return {"critic": self.critic.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.critic.load_state_dict(state["critic"])


class WorstCaseValue(nn.Module):
    """A worst-attack Q of the task reward, and the term −κ·Q_w(s, ã) it gives the actor's loss."""

    def __init__(self, obs_dim: int, act_dim: int, threat: ThreatModel, hidden: int = 256, layers: int = 3,
                 lr: float = 3e-4, gamma: float = 0.99, tau: float = 0.005, steps: int = 10):
        super().__init__()
        self.q = mlp(obs_dim + act_dim, 1, hidden, layers)
        self.q_target = copy.deepcopy(self.q).requires_grad_(False)
        self.optimizer = adam(self.q.parameters(), lr)
        self.threat, self.gamma, self.tau, self.steps = threat, gamma, tau, steps
        self.kappa = 0.0

    def value(self, obs: torch.Tensor, action: torch.Tensor, target: bool = False) -> torch.Tensor:
        return (self.q_target if target else self.q)(torch.cat([obs, action], -1)).squeeze(-1)

    def update(self, batch: dict[str, torch.Tensor], actor: TanhGaussianActor) -> dict[str, float]:
        """One step of the worst-attack Bellman operator on ``batch`` (the actor's weights are not touched)."""
        worst = worst_observation(actor, lambda o, a: self.value(o, a, target=True), batch["next_obs"], self.threat,
                                  self.steps)
        with torch.no_grad():
            next_q = self.value(batch["next_obs"], actor(worst), target=True)
            y = batch["reward"] + self.gamma * (1.0 - batch["terminated"]) * next_q
        loss = ((self.value(batch["obs"], batch["action"]) - y) ** 2).mean()
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        with torch.no_grad():
            torch._foreach_lerp_(list(self.q_target.parameters()), list(self.q.parameters()), self.tau)
        return {"worst_q_loss": loss.item(), "worst_q_mean": float(y.mean())}

    def __call__(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        self.q.requires_grad_(False)  # the term moves the actor, never Q_w
        try:
            return -self.kappa * self.value(obs, action)
        finally:
            self.q.requires_grad_(True)

    def optimizer_state(self) -> dict:
        return self.optimizer.state_dict()


def state_smoothness(actor: TanhGaussianActor, threat: ThreatModel, weight: float, steps: int = 5
                     ) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """λ·‖μ(s̃*) − μ(s)‖² per row, s̃* the ball's observation that moves μ most (SA-PPO's regulariser for SAC)."""

    def term(obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        clean = actor(obs).detach()
        moved = lambda o, a: ((a - clean) ** 2).sum(-1)  # noqa: E731
        worst = worst_observation(actor, moved, obs, threat, steps, sign=1.0)
        return weight * ((actor(worst) - clean) ** 2).sum(-1)

    return term


class Anchor:
    """λ·|Q̄|·‖ã − μ₀(s)‖² per row: ``start`` is μ₀ (frozen); |Q̄| is the batch's mean |min Q(s̃, ã)| under
    ``critic`` (the agent's own), taken as a constant, as TD3+BC scales its behaviour term.

    ``obs`` is what the agent saw (s̃, where ã was drawn) and ``true_obs`` the unperturbed observation at which
    μ₀ is taken. Anchored at s̃ instead, the agent is held to the starting actor's answer to the perturbation,
    which is what the attack exploits (benchmarks/table3.md#the-anchor-at-the-true-observation)."""

    def __init__(self, start: TanhGaussianActor, critic: TwinCritic, weight: float):
        self.start, self.critic, self.weight = start.requires_grad_(False), critic, weight

    def __call__(self, obs: torch.Tensor, action: torch.Tensor, true_obs: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            reference = self.start(true_obs)
            scale = torch.min(*self.critic(obs, action)).abs().mean()
        return self.weight * scale * ((action - reference) ** 2).sum(-1)
