"""A replay buffer that bootstraps through time limits and can be relabelled.

Only true terminations stop bootstrapping: an episode cut by the horizon (truncation) still
bootstraps from its last next-observation, as the MDP goes on beyond the cut.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

FIELDS = ("obs", "action", "reward", "next_obs", "terminated")


class ReplayBuffer:
    """A ring buffer of transitions ``(obs, action, reward, next_obs, terminated)``.

    Args:
        obs_dim, act_dim: sizes of one observation and one action.
        capacity: number of transitions kept; the oldest are overwritten.
    """

    def __init__(self, obs_dim: int, act_dim: int, capacity: int):
        self.capacity = int(capacity)
        self.obs = np.zeros((capacity, obs_dim), np.float32)
        self.action = np.zeros((capacity, act_dim), np.float32)
        self.reward = np.zeros((capacity,), np.float32)
        self.next_obs = np.zeros((capacity, obs_dim), np.float32)
        self.terminated = np.zeros((capacity,), np.float32)
        self.size = 0
        self.cursor = 0

    def __len__(self) -> int:
        return self.size

    def add(self, obs, action, reward: float, next_obs, terminated: bool) -> None:
        """Store one transition. Pass ``terminated`` only, never ``truncated``."""
        i = self.cursor
        self.obs[i], self.action[i], self.reward[i] = obs, action, reward
        self.next_obs[i], self.terminated[i] = next_obs, float(terminated)
        self.cursor = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size: int, rng: np.random.Generator, device: str | torch.device = "cpu") -> dict[str, torch.Tensor]:
        """A uniform batch of stored transitions as tensors, drawn with ``rng``."""
        return self.take(self.sample_indices(batch_size, rng), device)

    def sample_indices(self, batch_size: int, rng: np.random.Generator) -> np.ndarray:
        """Where a uniform batch lies (for data kept beside the buffer, row for row)."""
        return rng.integers(0, self.size, size=batch_size)

    def take(self, idx: np.ndarray, device: str | torch.device = "cpu") -> dict[str, torch.Tensor]:
        """The transitions at ``idx`` as tensors."""
        return {name: torch.as_tensor(getattr(self, name)[idx], device=device) for name in FIELDS}

    @property
    def last_index(self) -> int:
        """Where the latest transition was stored."""
        return (self.cursor - 1) % self.capacity

    def relabel(self, reward_fn: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray], chunk: int = 8192) -> None:
        """Rewrite every stored reward as ``reward_fn(obs, action, next_obs)`` (batched numpy)."""
        for start in range(0, self.size, chunk):
            end = min(start + chunk, self.size)
            self.reward[start:end] = reward_fn(self.obs[start:end], self.action[start:end], self.next_obs[start:end])

    def state_dict(self) -> dict[str, np.ndarray]:
        """The stored transitions and cursor, for a checkpoint."""
        state = {name: getattr(self, name)[: self.size] for name in FIELDS}
        state["meta"] = np.array([self.size, self.cursor, self.capacity], np.int64)
        return state

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        size, cursor, capacity = (int(x) for x in state["meta"])
        if capacity != self.capacity:
            raise ValueError(f"buffer capacity {capacity} in checkpoint differs from {self.capacity}")
        for name in FIELDS:
            getattr(self, name)[:size] = state[name]
        self.size, self.cursor = size, cursor
