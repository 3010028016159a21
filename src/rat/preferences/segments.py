"""Trajectory segments: what a teacher compares.

A segment is ``length`` consecutive steps of one episode: observations ``[L, obs_dim]``,
actions ``[L, act_dim]`` and, where known, the true target reward ``[L]`` (used only by a
scripted teacher and by evaluation, never by the learner).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from rat.errors import RatError


@dataclass
class SegmentPairs:
    """``n`` pairs of segments, arrays stacked along the first axis.

    ``obs0 [n, L, obs_dim]``, ``act0 [n, L, act_dim]``, ``reward0 [n, L]`` (true target reward,
    NaN where unknown), and the same for the second segment (suffix 1).
    """

    obs0: np.ndarray
    act0: np.ndarray
    reward0: np.ndarray
    obs1: np.ndarray
    act1: np.ndarray
    reward1: np.ndarray

    def __len__(self) -> int:
        return len(self.obs0)

    def select(self, idx) -> "SegmentPairs":
        return SegmentPairs(*(a[idx] for a in self.arrays()))

    def arrays(self) -> tuple[np.ndarray, ...]:
        return self.obs0, self.act0, self.reward0, self.obs1, self.act1, self.reward1


class EpisodeHistory:
    """The most recent complete episodes, for drawing segments.

    Args:
        max_episodes: episodes kept (PEBBLE: 100); older ones are dropped.
    """

    def __init__(self, max_episodes: int = 100):
        self.episodes: deque[tuple[np.ndarray, np.ndarray, np.ndarray]] = deque(maxlen=max_episodes)
        self._obs: list[np.ndarray] = []
        self._act: list[np.ndarray] = []
        self._rew: list[float] = []

    def add(self, obs: np.ndarray, action: np.ndarray, target_reward: float, episode_end: bool) -> None:
        """Record one step; ``episode_end`` closes the episode (termination or truncation)."""
        self._obs.append(np.asarray(obs, np.float32))
        self._act.append(np.asarray(action, np.float32))
        self._rew.append(float(target_reward))
        if episode_end:
            self.end_episode()

    def end_episode(self) -> None:
        if self._obs:
            self.episodes.append((np.stack(self._obs), np.stack(self._act), np.asarray(self._rew, np.float32)))
        self._obs, self._act, self._rew = [], [], []

    def __len__(self) -> int:
        return len(self.episodes)

    def with_current(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The stored episodes and the one in progress (if it has begun)."""
        episodes = list(self.episodes)
        if self._obs:
            episodes.append((np.stack(self._obs), np.stack(self._act), np.asarray(self._rew, np.float32)))
        return episodes

    def sample_pairs(self, n: int, length: int, rng: np.random.Generator) -> SegmentPairs:
        """``n`` pairs of segments of ``length`` steps, each from a uniformly drawn stored episode
        (the episode in progress counts too)."""
        usable = [e for e in self.with_current() if len(e[0]) >= length]
        if not usable:
            raise RatError(f"no episode has {length} steps yet to draw segments from; "
                           "start the first query round later or shorten the segments")
        halves = []
        for _ in range(2):
            ep = rng.integers(0, len(usable), size=n)
            parts = []
            for i in ep:
                obs, act, rew = usable[i]
                start = rng.integers(0, len(obs) - length + 1)
                parts.append((obs[start:start + length], act[start:start + length], rew[start:start + length]))
            halves.append([np.stack(x) for x in zip(*parts)])
        return SegmentPairs(*halves[0], *halves[1])

    def state_dict(self) -> dict:
        return {"episodes": [list(e) for e in self.episodes], "current": [np.asarray(self._obs), np.asarray(self._act),
                                                                        np.asarray(self._rew, np.float32)],
                "max_episodes": self.episodes.maxlen}

    def load_state_dict(self, state: dict) -> None:
        self.episodes = deque((tuple(e) for e in state["episodes"]), maxlen=int(state["max_episodes"]))
        obs, act, rew = state["current"]
        self._obs, self._act, self._rew = list(obs), list(act), list(rew)
