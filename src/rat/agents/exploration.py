"""Unsupervised exploration by state entropy (PEBBLE's pre-training).

The intrinsic reward of a state is its distance to the k-th nearest neighbour among the replay
buffer's observations (a particle estimate of state entropy), divided by a running standard
deviation so its scale stays steady as the buffer grows.
"""

from __future__ import annotations

import numpy as np
import torch


def knn_distance(obs: torch.Tensor, pool: torch.Tensor, k: int = 5, chunk: int = 10_000) -> torch.Tensor:
    """Distance from each row of ``obs [B, d]`` to its k-th nearest neighbour in ``pool [N, d]``.

    ``obs`` rows are assumed to be in ``pool`` too, so their zero distance to themselves is
    skipped: the result is the (k+1)-th smallest distance, as in PEBBLE.
    """
    nearest = []
    for start in range(0, len(pool), chunk):
        d = torch.cdist(obs, pool[start:start + chunk])
        nearest.append(torch.topk(d, min(k + 1, d.shape[1]), dim=1, largest=False).values)
    merged = torch.cat(nearest, dim=1)
    return torch.topk(merged, min(k + 1, merged.shape[1]), dim=1, largest=False).values[:, -1]


class RunningMeanStd:
    """Running mean and variance over batches (parallel-update formula)."""

    def __init__(self, epsilon: float = 1e-4):
        self.mean, self.var, self.count = 0.0, 1.0, epsilon

    def update(self, x: np.ndarray) -> None:
        x = np.asarray(x, np.float64)
        b_mean, b_var, b_count = x.mean(), x.var(), x.size
        delta, total = b_mean - self.mean, self.count + b_count
        self.mean = self.mean + delta * b_count / total
        m2 = self.var * self.count + b_var * b_count + delta**2 * self.count * b_count / total
        self.var, self.count = m2 / total, total

    @property
    def std(self) -> float:
        return float(np.sqrt(self.var))

    def state_dict(self) -> dict:
        return {"mean": self.mean, "var": self.var, "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.mean, self.var, self.count = float(state["mean"]), float(state["var"]), float(state["count"])


def state_entropy_reward(obs: torch.Tensor, pool: torch.Tensor, stats: RunningMeanStd, k: int = 5) -> torch.Tensor:
    """PEBBLE's intrinsic reward: k-NN distance, normalised by its running std (``stats`` is updated)."""
    distance = knn_distance(obs, pool, k)
    stats.update(distance.cpu().numpy())
    return distance / max(stats.std, 1e-8)
