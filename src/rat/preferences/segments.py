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
    NaN where unknown), and the same for the second segment (suffix 1). ``physics``, where the
    run recorded it (to film the segments for a person): ``states0 [n, L, S]``, ``states1``,
    ``scene0 [n, K]``, ``scene1`` (see :mod:`rat.envs.physics`).
    """

    obs0: np.ndarray
    act0: np.ndarray
    reward0: np.ndarray
    obs1: np.ndarray
    act1: np.ndarray
    reward1: np.ndarray
    physics: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self.obs0)

    def select(self, idx) -> SegmentPairs:
        physics = tuple(a[idx] for a in self.physics) if self.physics is not None else None
        return SegmentPairs(*(a[idx] for a in self.arrays()), physics=physics)

    def arrays(self) -> tuple[np.ndarray, ...]:
        return self.obs0, self.act0, self.reward0, self.obs1, self.act1, self.reward1


class EpisodeHistory:
    """The most recent complete episodes, for drawing segments.

    An episode is ``(obs [T, d], act [T, a], target reward [T])``, followed by ``(physics states
    [T, S], scene [K])`` when its steps came with physics (see :meth:`add`).

    Args:
        max_episodes: episodes kept (PEBBLE: 100); older ones are dropped.
    """

    def __init__(self, max_episodes: int = 100):
        self.episodes: deque[tuple[np.ndarray, ...]] = deque(maxlen=max_episodes)
        self._obs: list[np.ndarray] = []
        self._act: list[np.ndarray] = []
        self._rew: list[float] = []
        self._states: list[np.ndarray] = []
        self._scene: np.ndarray | None = None

    def add(self, obs: np.ndarray, action: np.ndarray, target_reward: float, episode_end: bool,
            physics: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Record one step; ``episode_end`` closes the episode (termination or truncation).
        ``physics``: the step's physics state and its episode's scene, to film it later."""
        self._obs.append(np.asarray(obs, np.float32))
        self._act.append(np.asarray(action, np.float32))
        self._rew.append(float(target_reward))
        if physics is not None:
            self._states.append(np.asarray(physics[0], np.float64))
            if self._scene is None:
                self._scene = np.asarray(physics[1], np.float64)
        if episode_end:
            self.end_episode()

    def _current(self) -> tuple[np.ndarray, ...]:
        episode = (np.stack(self._obs), np.stack(self._act), np.asarray(self._rew, np.float32))
        if self._states and len(self._states) == len(self._obs):
            episode += (np.stack(self._states), self._scene)
        return episode

    def end_episode(self) -> None:
        if self._obs:
            self.episodes.append(self._current())
        self._obs, self._act, self._rew, self._states, self._scene = [], [], [], [], None

    def __len__(self) -> int:
        return len(self.episodes)

    def with_current(self) -> list[tuple[np.ndarray, ...]]:
        """The stored episodes and the one in progress (if it has begun)."""
        episodes = list(self.episodes)
        if self._obs:
            episodes.append(self._current())
        return episodes

    def sample_pairs(self, n: int, length: int, rng: np.random.Generator) -> SegmentPairs:
        """``n`` pairs of segments of ``length`` steps, each from a uniformly drawn stored episode
        (the episode in progress counts too)."""
        usable = [e for e in self.with_current() if len(e[0]) >= length]
        if not usable:
            raise RatError(f"no episode has {length} steps yet to draw segments from; "
                           "start the first query round later or shorten the segments")
        filmed = all(len(e) == 5 for e in usable)
        halves, states, scenes = [], [], []
        for _ in range(2):
            ep = rng.integers(0, len(usable), size=n)
            parts, half_states, half_scenes = [], [], []
            for i in ep:
                episode = usable[i]
                start = rng.integers(0, len(episode[0]) - length + 1)
                parts.append(tuple(x[start:start + length] for x in episode[:3]))
                if filmed:
                    half_states.append(episode[3][start:start + length])
                    half_scenes.append(episode[4])
            halves.append([np.stack(x) for x in zip(*parts)])
            states.append(half_states)
            scenes.append(half_scenes)
        physics = tuple(np.stack(x) for x in (*states, *scenes)) if filmed else None  # states0, states1, scene0, scene1
        return SegmentPairs(*halves[0], *halves[1], physics=physics)

    def state_dict(self) -> dict:
        current = [np.asarray(self._obs), np.asarray(self._act), np.asarray(self._rew, np.float32)]
        if self._states:
            current += [np.asarray(self._states), self._scene]
        return {"episodes": [list(e) for e in self.episodes], "current": current, "max_episodes": self.episodes.maxlen}

    def load_state_dict(self, state: dict) -> None:
        self.episodes = deque((tuple(e) for e in state["episodes"]), maxlen=int(state["max_episodes"]))
        obs, act, rew, *physics = state["current"]
        self._obs, self._act, self._rew = list(obs), list(act), list(rew)
        self._states, self._scene = (list(physics[0]), physics[1]) if physics else ([], None)
