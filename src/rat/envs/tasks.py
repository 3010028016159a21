"""Every task by name: Meta-World v3 manipulation (``drawer-open-v3``, ...) and Gymnasium MuJoCo
locomotion (``HalfCheetah-v5``, ``Walker2d-v5``)."""

from __future__ import annotations

import difflib

import gymnasium as gym

from rat.envs import metaworld
from rat.envs.locomotion import LOCOMOTION_TASKS, make_locomotion
from rat.errors import RatError


def all_tasks() -> list[str]:
    """Every task name: Meta-World's v3 tasks and the locomotion tasks."""
    return metaworld.all_tasks() + list(LOCOMOTION_TASKS)


def check_task(task: str) -> str:
    """Return ``task`` if it is known, else raise a one-line error naming the fix."""
    tasks = all_tasks()
    if task not in tasks:
        close = difflib.get_close_matches(task, tasks, n=1)
        hint = f"did you mean '{close[0]}'? " if close else ""
        raise RatError(f"unknown task '{task}': {hint}run `rat list tasks` for the names")
    return task


def episode_length(env: gym.Env, default: int = metaworld.HORIZON) -> int:
    """The environment's time limit (its spec's ``max_episode_steps``), else ``default``."""
    return int(getattr(getattr(env, "spec", None), "max_episode_steps", None) or default)


def make_task(task: str, seed: int = 0, render_mode: str | None = None, **kwargs) -> gym.Env:
    """Make a task by name: a :class:`~rat.envs.metaworld.MetaWorldTask` or a
    :class:`~rat.envs.locomotion.LocomotionTask`."""
    if task in LOCOMOTION_TASKS:
        return make_locomotion(task, seed=seed, render_mode=render_mode)
    return metaworld.make_task(task, seed=seed, render_mode=render_mode, **kwargs)
