"""The learned reward r̂_ψ: an ensemble of MLPs trained on preferences with Bradley–Terry.

Each member maps ``s ‖ a`` (optionally standardised, ``normalize_inputs``) through 3×256 LeakyReLU
layers to one tanh-bounded reward; r̂ is the ensemble mean. A member's preference predictor is

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
    #: standardise each input feature by its mean and spread over the labelled segments, refit every round
    #: (a departure from PEBBLE, whose members see raw ``s ‖ a``; see :meth:`RewardEnsemble.fit_inputs`)
    normalize_inputs: bool = False


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
        if config.normalize_inputs:  # buffers, so checkpoints keep them; absent otherwise, so older ones still load
            self.register_buffer("input_mean", torch.zeros(obs_dim + act_dim))
            self.register_buffer("input_std", torch.ones(obs_dim + act_dim))

    @property
    def _device(self) -> torch.device:
        return next(self.parameters()).device

    def _inputs(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        x = torch.cat([obs, action], dim=-1)
        return (x - self.input_mean) / self.input_std if self.config.normalize_inputs else x

    @staticmethod
    def _reward(net: nn.Module, x: torch.Tensor) -> torch.Tensor:
        return torch.tanh(net(x)).squeeze(-1)

    def member_rewards(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Rewards of every member, ``[members, ...]`` for inputs ``[..., dim]``."""
        x = self._inputs(obs, action)
        return torch.stack([self._reward(net, x) for net in self.nets])

    #: the least spread a feature is divided by: a feature nearly constant over the labels (a goal slot, a
    #: fixed quaternion) is not blown up where a later state moves it
    MIN_STD = 1e-2

    @torch.no_grad()
    def fit_inputs(self, obs: list[np.ndarray], actions: list[np.ndarray]) -> None:
        """Set the standardisation (``normalize_inputs``) from transitions: arrays ``[..., dim]``, paired in order
        (a round passes both segments of every label so far).

        The features of ``s ‖ a`` differ in scale by orders of magnitude (positions in metres, quaternions, the
        gripper, actions in [−1, 1]); raw, the members are slow to resolve the centimetres a reward may turn
        on. What it does to r̂ and to the attack: benchmarks/strength.md.
        """
        total, square, n = 0.0, 0.0, 0
        for o, a in zip(obs, actions):
            for i in range(0, len(o), 1024):  # in chunks: 9,000 labels' segments are 10⁶ rows
                x = torch.as_tensor(np.concatenate([o[i:i + 1024], a[i:i + 1024]], -1), dtype=torch.float64)
                x = x.reshape(-1, self.obs_dim + self.act_dim)
                total, square, n = total + x.sum(0), square + (x * x).sum(0), n + len(x)
        mean = total / n
        std = (square / n - mean * mean).clamp_min(0.0).sqrt()
        self.input_mean.copy_(mean.float())
        self.input_std.copy_(std.float().clamp_min(self.MIN_STD))

    @torch.no_grad()
    def r_hat(self, obs: np.ndarray, action: np.ndarray, chunk: int = 8192) -> np.ndarray:
        """The ensemble-mean reward of transitions (numpy in and out, batched over the leading axes; ``chunk``
        entries of the first axis at a time, so a whole replay buffer fits in memory)."""
        if np.ndim(obs) > 1 and len(obs) > chunk:
            return np.concatenate([self.r_hat(obs[i:i + chunk], action[i:i + chunk]) for i in range(0, len(obs), chunk)])
        o = torch.as_tensor(obs, dtype=torch.float32, device=self._device)
        a = torch.as_tensor(action, dtype=torch.float32, device=self._device)
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
        if cfg.normalize_inputs:  # every label so far, both segments
            self.fit_inputs([obs0, obs1], [act0, act1])
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
                    r0 = self._reward(net, self._inputs(o0, a0)).sum(-1)
                    r1 = self._reward(net, self._inputs(o1, a1)).sum(-1)
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


def reward_agreement(learned: np.ndarray, true: np.ndarray, segment: int, pairs: int = 20_000) -> dict[str, float]:
    """How a learned reward agrees with a true one over the same steps, given in order, whole segments of
    ``segment`` steps back to back: the per-step correlation, the correlation of segment returns, and, of
    ``pairs`` random pairs of segments (drawn with a fixed seed) whose true returns differ, the share that the
    learned returns order as the true ones do. A score is left out where it is undefined (a constant reward,
    no decided pair)."""
    learned, true = np.asarray(learned, np.float64).reshape(-1), np.asarray(true, np.float64).reshape(-1)
    m = len(true) // segment * segment
    seg_learned, seg_true = learned[:m].reshape(-1, segment).sum(1), true[:m].reshape(-1, segment).sum(1)

    scores = {}
    for name, (x, y) in {"step_corr": (learned, true), "segment_corr": (seg_learned, seg_true)}.items():
        if len(x) >= 2 and x.std() > 0 and y.std() > 0:
            scores[name] = float(np.corrcoef(x, y)[0, 1])
    i, j = np.random.default_rng(0).integers(len(seg_true), size=(2, pairs)) if len(seg_true) else np.zeros((2, 0), int)
    decided = seg_true[i] != seg_true[j]
    if decided.any():
        right = np.sign(seg_learned[i] - seg_learned[j]) == np.sign(seg_true[i] - seg_true[j])
        scores["pairs_ordered"] = float(right[decided].mean())
    return scores
