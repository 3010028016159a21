"""The learned reward r̂_ψ: an ensemble of MLPs trained on preferences with Bradley–Terry.

Each member maps ``s ‖ a`` through 3×256 LeakyReLU layers to one tanh-bounded reward; r̂ is the
ensemble mean. A member's preference predictor is

    P[σ¹ ≻ σ⁰] = exp Σ r̂(σ¹) / (exp Σ r̂(σ⁰) + exp Σ r̂(σ¹)) = sigmoid(Σ r̂(σ¹) − Σ r̂(σ⁰)),

trained with cross-entropy against the label y = P[σ¹ ≻ σ⁰] (see :mod:`rat.preferences.teacher`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from rat.agents.networks import mlp


@dataclass(frozen=True)
class RewardModelConfig:
    """Reward ensemble settings (PEBBLE's defaults)."""

    members: int = 3  #: ensemble size
    hidden: int = 256  #: width of hidden layers
    layers: int = 3  #: hidden layers
    lr: float = 3e-4  #: Adam learning rate
    batch_size: int = 128  #: labelled pairs per gradient step
    max_epochs: int = 200  #: epochs per training round, at most
    max_updates: int | None = None  #: gradient steps per member per round, at most (None: no cap; rounds then grow with the labels)
    stop_accuracy: float = 0.97  #: stop a round once training accuracy exceeds this


def bradley_terry_loss(return0: torch.Tensor, return1: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of ``sigmoid(return1 - return0)`` against ``y`` (= P[σ¹ ≻ σ⁰]), mean over pairs."""
    logits = torch.stack([return0, return1], dim=-1)
    target = torch.stack([1.0 - y, y], dim=-1)
    return -(target * F.log_softmax(logits, dim=-1)).sum(-1).mean()


class RewardEnsemble(nn.Module):
    """``members`` reward networks with their own optimisers."""

    def __init__(self, obs_dim: int, act_dim: int, config: RewardModelConfig = RewardModelConfig()):
        super().__init__()
        self.config = config
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.nets = nn.ModuleList(
            mlp(obs_dim + act_dim, 1, config.hidden, config.layers, activation=nn.LeakyReLU) for _ in range(config.members))
        self.optimizers = [torch.optim.Adam(n.parameters(), lr=config.lr) for n in self.nets]
        self.rounds = 0
        self.epochs_run = 0

    @property
    def _device(self) -> torch.device:
        return next(self.parameters()).device

    def member_rewards(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Rewards of every member, ``[members, ...]`` for inputs ``[..., dim]``."""
        x = torch.cat([obs, action], dim=-1)
        return torch.stack([torch.tanh(net(x)).squeeze(-1) for net in self.nets])

    @torch.no_grad()
    def r_hat(self, obs: np.ndarray, action: np.ndarray) -> np.ndarray:
        """The ensemble-mean reward of transitions (numpy in and out, batched over the leading axes)."""
        device = self._device
        o = torch.as_tensor(obs, dtype=torch.float32, device=device)
        a = torch.as_tensor(action, dtype=torch.float32, device=device)
        return self.member_rewards(o, a).mean(0).cpu().numpy()

    @torch.no_grad()
    def preference_probabilities(self, obs0, act0, obs1, act1) -> np.ndarray:
        """Each member's P[σ¹ ≻ σ⁰] for every pair: ``[members, n]``."""
        d = self._device
        r0 = self.member_rewards(torch.as_tensor(obs0, device=d), torch.as_tensor(act0, device=d)).sum(-1)
        r1 = self.member_rewards(torch.as_tensor(obs1, device=d), torch.as_tensor(act1, device=d)).sum(-1)
        return torch.sigmoid(r1 - r0).cpu().numpy()

    def train_round(self, obs0, act0, obs1, act1, y, rng: np.random.Generator) -> dict[str, float]:
        """Train every member on all labels until accuracy > ``stop_accuracy`` or ``max_epochs``.

        Each member sees its own shuffles of the data (``rng``). Equal labels (0.5) count as
        correct for accuracy, as in B-Pref. Returns the round's metrics.
        """
        cfg = self.config
        data = [torch.as_tensor(np.asarray(a, np.float32), device=self._device) for a in (obs0, act0, obs1, act1, y)]
        n = len(data[-1])
        updates = 0
        for epoch in range(cfg.max_epochs):
            correct, total_loss = np.zeros(cfg.members), 0.0
            batches = -(-n // cfg.batch_size)
            if cfg.max_updates is not None:  # the last epoch may be cut short: a random part of the labels
                batches = min(batches, cfg.max_updates - updates)
            for m, (net, opt) in enumerate(zip(self.nets, self.optimizers)):
                order = torch.as_tensor(rng.permutation(n))
                for start in range(0, batches * cfg.batch_size, cfg.batch_size):
                    idx = order[start:start + cfg.batch_size]
                    o0, a0, o1, a1, yy = (d[idx] for d in data)
                    r0 = torch.tanh(net(torch.cat([o0, a0], -1))).squeeze(-1).sum(-1)
                    r1 = torch.tanh(net(torch.cat([o1, a1], -1))).squeeze(-1).sum(-1)
                    loss = bradley_terry_loss(r0, r1, yy)
                    opt.zero_grad(set_to_none=True)
                    loss.backward()
                    opt.step()
                    total_loss += loss.item() * len(idx)
                    predicted = (r1 > r0).float()
                    correct[m] += ((predicted == yy) | (yy == 0.5)).sum().item()
            self.epochs_run += 1
            updates += batches
            seen = min(n, batches * cfg.batch_size)
            accuracy = correct.mean() / seen
            if accuracy > cfg.stop_accuracy or (cfg.max_updates is not None and updates >= cfg.max_updates):
                break
        self.rounds += 1
        return {"reward_train_accuracy": float(accuracy), "reward_loss": total_loss / (seen * cfg.members),
                "reward_epochs": float(epoch + 1), "reward_updates": float(updates)}

    def optimizer_state(self) -> dict:
        return {"optimizers": [o.state_dict() for o in self.optimizers], "rounds": self.rounds,
                "epochs_run": self.epochs_run}

    def load_optimizer_state(self, state: dict) -> None:
        for o, s in zip(self.optimizers, state["optimizers"]):
            o.load_state_dict(s)
        self.rounds, self.epochs_run = int(state["rounds"]), int(state["epochs_run"])
