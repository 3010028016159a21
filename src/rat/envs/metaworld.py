"""Meta-World v3 single tasks, as the paper uses them.

Each reset re-draws the object and goal positions; the sequence of draws is reproducible from
the seed. The horizon is Meta-World's own 500 steps (reported as truncation, never as
termination). ``info`` always carries, besides Meta-World's own keys:

``tcp_pos``        the tool centre point (between the fingers), metres, after the step
``prev_tcp_pos``   the tool centre point before the step
``tcp_init``       the tool centre point right after reset
``obj_pos``        the task object's position (first object, metres)
``goal_pos``       the task's goal position (metres)
``task_reward``    the task's own reward for the step
``success``        the task's own success test at this step (bool)
"""

from __future__ import annotations

import os
from typing import Any

import gymnasium as gym
import numpy as np

from rat.errors import RatError

#: The eight tasks of the paper, and each one's opposite behaviour.
PAPER_TASKS: dict[str, str] = {
    "door-lock-v3": "door-unlock-v3",
    "door-unlock-v3": "door-lock-v3",
    "drawer-open-v3": "drawer-close-v3",
    "drawer-close-v3": "drawer-open-v3",
    "faucet-open-v3": "faucet-close-v3",
    "faucet-close-v3": "faucet-open-v3",
    "window-open-v3": "window-close-v3",
    "window-close-v3": "window-open-v3",
}

HORIZON = 500
OBS_DIM = 39
ACT_DIM = 4


def all_tasks() -> list[str]:
    """Every Meta-World v3 task name this installation offers."""
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    return sorted(ALL_V3_ENVIRONMENTS)


class MetaWorldTask(gym.Env):
    """One Meta-World v3 task with a goal re-drawn at every reset.

    Args:
        task: a Meta-World v3 name such as ``"drawer-open-v3"``.
        seed: seeds the sequence of object and goal positions; ``reset(seed=s)`` restarts it.
        render_mode: ``"rgb_array"`` to record videos (needs an OpenGL backend; ``MUJOCO_GL=egl``
            is chosen when nothing else is set).
        camera: Meta-World camera name for rendering.
        size: rendered frame size in pixels (square).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 80}

    def __init__(
        self,
        task: str,
        seed: int = 0,
        render_mode: str | None = None,
        camera: str = "corner2",
        size: int = 224,
    ):
        from metaworld.env_dict import ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE

        if task not in all_tasks():
            from rat.envs.tasks import check_task

            check_task(task)  # the one-line error with the closest name; or, for a locomotion task:
            raise RatError(f"'{task}' is not a Meta-World task; make it with rat.envs.make_task")
        if render_mode is not None:
            os.environ.setdefault("MUJOCO_GL", "egl")
        cls = ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE[f"{task}-goal-observable"]
        self._env = cls(seed=seed, render_mode=render_mode)
        if render_mode is not None:
            from gymnasium.envs.mujoco.mujoco_rendering import MujocoRenderer

            from rat.envs.physics import fit_shadow_map

            self._env.mujoco_renderer.close()
            fit_shadow_map(self._env.model, size)
            self._env.mujoco_renderer = MujocoRenderer(self._env.model, self._env.data, None, size, size,
                                                       camera_name=camera)
        self._env._freeze_rand_vec = False  # a new object and goal at every reset
        self._env.seeded_rand_vec = True  # ... drawn from the env's own seeded generator
        self._env.seed(seed)
        self.task = task
        self.render_mode = render_mode
        self.action_space = gym.spaces.Box(-1.0, 1.0, (ACT_DIM,), np.float32)
        # Meta-World's declared space has stale (0, 0) goal bounds; declare what is observed.
        low = np.array(self._env.observation_space.low, dtype=np.float64)
        high = np.array(self._env.observation_space.high, dtype=np.float64)
        low[36:39], high[36:39] = -np.inf, np.inf
        self.observation_space = gym.spaces.Box(low, high, dtype=np.float64)
        self.spec = gym.envs.registration.EnvSpec(f"rat/{task}", max_episode_steps=HORIZON)
        self._tcp_init = np.zeros(3)

    @property
    def unwrapped_metaworld(self):
        """The underlying Meta-World environment (for expert policies and diagnostics)."""
        return self._env

    def _extra_info(self, prev_tcp: np.ndarray) -> dict[str, Any]:
        env = self._env
        return {
            "tcp_pos": np.array(env.tcp_center, dtype=np.float64),
            "prev_tcp_pos": prev_tcp,
            "tcp_init": self._tcp_init.copy(),
            "obj_pos": np.array(env._get_pos_objects()[:3], dtype=np.float64),
            "goal_pos": np.array(env._target_pos, dtype=np.float64),
        }

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._env.seed(seed)
        obs, _ = self._env.reset()
        self._tcp_init = np.array(self._env.tcp_center, dtype=np.float64)
        info = self._extra_info(self._tcp_init.copy())
        info["success"] = False
        info["task_reward"] = 0.0
        return obs.astype(np.float64), info

    def step(self, action):
        prev_tcp = np.array(self._env.tcp_center, dtype=np.float64)
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        obs, reward, terminated, truncated, info = self._env.step(action)
        info = dict(info)
        info.update(self._extra_info(prev_tcp))
        info["task_reward"] = float(reward)
        info["success"] = bool(info.get("success", 0.0) > 0.5)
        return obs.astype(np.float64), float(reward), bool(terminated), bool(truncated), info

    def render(self):
        if self.render_mode is None:
            raise RatError("this environment was made without render_mode; pass render_mode='rgb_array'")
        frame = self._env.render()
        # Meta-World's cameras come out upside down: turn the image by 180 degrees.
        return np.ascontiguousarray(frame[::-1, ::-1])

    def close(self):
        if self.render_mode is not None:
            self._env.mujoco_renderer.close()  # free the GL context now, not at interpreter exit
        self._env.close()


def make_task(task: str, seed: int = 0, render_mode: str | None = None, **kwargs) -> MetaWorldTask:
    """Make a Meta-World v3 task (see :class:`MetaWorldTask`)."""
    return MetaWorldTask(task, seed=seed, render_mode=render_mode, **kwargs)
