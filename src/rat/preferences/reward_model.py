"""The learned reward r̂_ψ: an ensemble of MLPs trained on preferences with Bradley–Terry.

Each member maps ``s ‖ a`` (optionally standardised, ``normalize_inputs``) through 3×256 LeakyReLU
layers to one tanh-bounded reward; r̂ is the ensemble mean. A member's preference predictor is

    P[σ¹ ≻ σ⁰] = exp Σ r̂(σ¹) / (exp Σ r̂(σ⁰) + exp Σ r̂(σ¹)) = sigmoid(Σ r̂(σ¹) − Σ r̂(σ⁰)),

trained with cross-entropy against the label y = P[σ¹ ≻ σ⁰] (see :mod:`rat.preferences.teacher`).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from rat.agents.networks import PRECISIONS, adam, keep_fused, mixed_precision, mlp
from rat.errors import RatError


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
    #: share of the labels held out of training to stop a round (0: PEBBLE's rounds, every label every epoch until
    #: ``stop_accuracy``). Above 0 a round trains on the labels new since the last round and as many old ones drawn
    #: at random, checks each member's held-out loss every ``check_every`` updates, stops the member after
    #: ``patience`` checks without a better one and keeps its best weights (a departure: benchmarks/speed.md)
    holdout: float = 0.0
    check_every: int = 25  #: updates of a member between held-out checks (``holdout`` > 0)
    patience: int = 2  #: held-out checks without improvement before a member stops (``holdout`` > 0)
    #: arithmetic of the hidden layers in training and relabelling: "fp32" or "bf16" (autocast; the output
    #: layer, weights and Adam stay float32)
    precision: str = "fp32"

    def __post_init__(self):
        if self.precision not in PRECISIONS:
            raise RatError(f"unknown reward-model precision '{self.precision}'; use one of: {', '.join(PRECISIONS)}")
        if not 0.0 <= self.holdout < 0.5:
            raise RatError(f"reward-model holdout must lie in [0, 0.5), got {self.holdout}")


def _correct(r0: torch.Tensor, r1: torch.Tensor, y: torch.Tensor) -> int:
    """Pairs whose predicted returns order them as the label does; equal labels (0.5) count as right (B-Pref)."""
    return int((((r1 > r0).float() == y) | (y == 0.5)).sum())


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
        self.optimizers = [adam(n.parameters(), config.lr) for n in self.nets]
        self.rounds = 0
        self.epochs_run = 0
        self.labels_trained = 0  #: labels the last round held (those after it are new to the next)
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
        on. What it does to r̂ and to the attack: docs/notes/strength-log.md.
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
        with mixed_precision(self.config.precision, self._device):
            return self.member_rewards(o, a).mean(0).cpu().numpy()

    @torch.no_grad()
    def preference_probabilities(self, obs0, act0, obs1, act1) -> np.ndarray:
        """Each member's P[σ¹ ≻ σ⁰] for every pair: ``[members, n]``."""
        d = self._device
        r0 = self.member_rewards(torch.as_tensor(obs0, device=d), torch.as_tensor(act0, device=d)).sum(-1)
        r1 = self.member_rewards(torch.as_tensor(obs1, device=d), torch.as_tensor(act1, device=d)).sum(-1)
        return torch.sigmoid(r1 - r0).cpu().numpy()

    def _pair_returns(self, net: nn.Module, o0, a0, o1, a1) -> tuple[torch.Tensor, torch.Tensor]:
        """Both segments' predicted returns under one member, in one pass (``[pairs]`` each)."""
        with mixed_precision(self.config.precision, self._device):
            r = self._reward(net, self._inputs(torch.cat([o0, o1]), torch.cat([a0, a1]))).sum(-1)
        return r[:len(o0)], r[len(o0):]

    def _step(self, net: nn.Module, opt: torch.optim.Optimizer, batch: list[torch.Tensor]) -> tuple[float, int]:
        """One Bradley–Terry gradient step of a member on ``batch`` (o0, a0, o1, a1, y): its loss and the pairs it
        ordered right."""
        o0, a0, o1, a1, y = batch
        r0, r1 = self._pair_returns(net, o0, a0, o1, a1)
        loss = bradley_terry_loss(r0, r1, y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return loss.item(), _correct(r0, r1, y)

    def train_round(self, obs0, act0, obs1, act1, y, rng: np.random.Generator) -> dict[str, float]:
        """Train every member on the labels, given in the order they were made (all of them so far).

        With ``holdout`` 0 (PEBBLE): on all labels until training accuracy > ``stop_accuracy`` or ``max_epochs``;
        otherwise stopped on held-out pairs (:meth:`_train_held_out`). Each member sees its own shuffles of the
        data (``rng``). Equal labels (0.5) count as correct for accuracy, as in B-Pref. Returns the round's metrics.
        """
        cfg = self.config
        if cfg.normalize_inputs:  # every label so far, both segments
            self.fit_inputs([obs0, obs1], [act0, act1])
        data = [torch.as_tensor(np.asarray(a, np.float32), device=self._device) for a in (obs0, act0, obs1, act1, y)]
        n = len(data[-1])
        if cfg.holdout > 0:
            metrics = self._train_held_out(data, rng)
            self.labels_trained = n
            self.rounds += 1
            return metrics
        updates = 0
        for epoch in range(cfg.max_epochs):  # noqa: B007 (the count is read after the loop)
            correct, total_loss = np.zeros(cfg.members), 0.0
            batches = -(-n // cfg.batch_size)
            if cfg.max_updates is not None:  # the last epoch may be cut short: a random part of the labels
                batches = min(batches, cfg.max_updates - updates)
            for m, (net, opt) in enumerate(zip(self.nets, self.optimizers)):
                order = torch.as_tensor(rng.permutation(n))
                for start in range(0, batches * cfg.batch_size, cfg.batch_size):
                    idx = order[start:start + cfg.batch_size]
                    loss, right = self._step(net, opt, [d[idx] for d in data])
                    total_loss += loss * len(idx)
                    correct[m] += right
            self.epochs_run += 1
            updates += batches
            seen = min(n, batches * cfg.batch_size)
            accuracy = correct.mean() / seen
            if accuracy > cfg.stop_accuracy or (cfg.max_updates is not None and updates >= cfg.max_updates):
                break
        self.rounds += 1
        self.labels_trained = n
        return {"reward_train_accuracy": float(accuracy), "reward_loss": total_loss / (seen * cfg.members),
                "reward_epochs": float(epoch + 1), "reward_updates": float(updates)}

    def held_out(self, n: int) -> np.ndarray:
        """Which of ``n`` labels (in the order made) are held out: every k-th, k = round(1 / ``holdout``), so a
        label keeps its side from round to round and no held-out pair is ever trained on."""
        k = max(2, round(1 / self.config.holdout))
        return np.arange(n) % k == k - 1

    @torch.no_grad()
    def _held_out_loss(self, net: nn.Module, data: list[torch.Tensor], idx: torch.Tensor) -> tuple[float, float]:
        """A member's mean Bradley–Terry loss and accuracy on the held-out pairs ``idx``."""
        loss, correct = 0.0, 0.0
        for start in range(0, len(idx), 4 * self.config.batch_size):
            o0, a0, o1, a1, yy = (d[idx[start:start + 4 * self.config.batch_size]] for d in data)
            r0, r1 = self._pair_returns(net, o0, a0, o1, a1)
            loss += bradley_terry_loss(r0, r1, yy).item() * len(yy)
            correct += _correct(r0, r1, yy)
        return loss / len(idx), correct / len(idx)

    def _train_held_out(self, data: list[torch.Tensor], rng: np.random.Generator) -> dict[str, float]:
        """A round stopped on held-out pairs: each member trains on the labels new since the last round and as
        many old ones (drawn afresh for each member), in shuffled passes, at most ``max_updates`` updates
        (``max_epochs`` passes); every ``check_every`` updates its held-out loss is measured, and after
        ``patience`` checks without a better one it stops and takes back the weights of its best check."""
        cfg = self.config
        n = len(data[-1])
        held = self.held_out(n)
        held_idx = torch.as_tensor(np.flatnonzero(held))
        train = np.flatnonzero(~held)
        if len(held_idx) == 0 or len(train) == 0:  # too few labels to hold any out: train on all, no stopping
            held_idx, train = torch.as_tensor(np.arange(n)), np.arange(n)
        new, old = train[train >= min(self.labels_trained, n)], train[train < min(self.labels_trained, n)]
        cap = cfg.max_updates if cfg.max_updates is not None else cfg.max_epochs * -(-len(train) // cfg.batch_size)
        totals = {"updates": 0, "loss": 0.0, "accuracy": 0.0, "train_accuracy": 0.0}
        for net, opt in zip(self.nets, self.optimizers):
            pool = np.concatenate([new, rng.choice(old, size=min(len(old), max(len(new), 1)), replace=False)])
            best_loss, best_acc = self._held_out_loss(net, data, held_idx)
            best_state, since_best, updates, correct, seen = copy.deepcopy(net.state_dict()), 0, 0, 0.0, 0
            while updates < cap and since_best < cfg.patience:
                order = torch.as_tensor(rng.permutation(pool))
                for start in range(0, len(order), cfg.batch_size):
                    idx = order[start:start + cfg.batch_size]
                    correct += self._step(net, opt, [d[idx] for d in data])[1]
                    seen, updates = seen + len(idx), updates + 1
                    if updates % cfg.check_every == 0 or updates == cap:
                        held_loss, held_acc = self._held_out_loss(net, data, held_idx)
                        if held_loss < best_loss:
                            best_loss, best_acc, best_state, since_best = held_loss, held_acc, copy.deepcopy(net.state_dict()), 0
                        else:
                            since_best += 1
                        if updates == cap or since_best >= cfg.patience:
                            break
                self.epochs_run += 1
            net.load_state_dict(best_state)
            totals["updates"] += updates
            totals["loss"] += best_loss
            totals["accuracy"] += best_acc
            totals["train_accuracy"] += correct / max(seen, 1)
        m = cfg.members
        return {"reward_train_accuracy": totals["train_accuracy"] / m, "reward_loss": totals["loss"] / m,
                "reward_heldout_accuracy": totals["accuracy"] / m, "reward_updates": totals["updates"] / m,
                "reward_new_labels": float(len(new) + np.count_nonzero(held[min(self.labels_trained, n):]))}

    def optimizer_state(self) -> dict:
        return {"optimizers": [o.state_dict() for o in self.optimizers], "rounds": self.rounds,
                "epochs_run": self.epochs_run, "labels_trained": self.labels_trained}

    def load_optimizer_state(self, state: dict) -> None:
        for o, s in zip(self.optimizers, state["optimizers"]):
            o.load_state_dict(s)
            keep_fused(o)
        self.rounds, self.epochs_run = int(state["rounds"]), int(state["epochs_run"])
        self.labels_trained = int(state["labels_trained"])


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
