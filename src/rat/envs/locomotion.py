"""Gymnasium MuJoCo locomotion tasks (the paper's case II) and their target behaviours.

:func:`make_locomotion` makes ``HalfCheetah-v5`` or ``Walker2d-v5`` with an ``info`` that carries
what the target behaviours read, from the simulator's state (the observation omits some of it):

- ``x_position``, ``prev_x_position``, ``start_x_position``: the torso's x after and before the
  step, and at the episode's start (metres);
- ``torso_z``: the torso's height; ``torso_pitch``: its rotation about y (radians, 0 upright for
  the walker and level for the cheetah, positive nose-down for the cheetah);
- Walker2d only: ``foot_z`` and ``foot_left_z`` (each foot's height) and ``thigh_angle`` and
  ``thigh_left_angle`` (hip joints; negative is the leg swung forward).

The target behaviours (registered with :func:`rat.envs.register_target`; success tests that need
the episode so far are stateful and count consecutive steps):

| name | victim | reward | success |
| --- | --- | --- | --- |
| ``cheetah-backward`` | HalfCheetah | −x-velocity | the torso 3 m behind where it started |
| ``cheetah-pushup`` | HalfCheetah | −‖pitch‖ − π/2‖ | pitched within 20° of vertical for 20 steps in a row |
| ``walker-one-foot`` | Walker2d | upright, one foot high, the other down, standing still | that, under 0.5 m/s, for 20 steps in a row |
| ``walker-leg-raised`` | Walker2d | upright, one leg swung forward and up | that for 100 steps in a row (0.8 s) |

Both walker tests are set against the clean walker, which must fail them: over 30 episodes our
Decision Transformer (``zoo:dt/walker2d-v5``) has one foot up and the other down for up to 43 steps
in a row in its swing phase, but never below 1.1 m/s once under way (so never for more than 11
such steps under 0.5 m/s), and its swinging leg is forward and up for up to 63 steps in a row.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from rat.errors import RatError

LOCOMOTION_TASKS = ("HalfCheetah-v5", "Walker2d-v5")

#: heights (metres) and angles (radians) of the success tests
UPRIGHT_Z, FOOT_UP, FOOT_DOWN, LEG_UP, THIGH_FORWARD = 0.9, 0.15, 0.1, 0.3, -0.6
PUSHUP_TOLERANCE, BACKWARD_DISTANCE, HOLD_STEPS = np.radians(20), 3.0, 20
STILL_SPEED, LEG_HOLD_STEPS = 0.5, 100  #: m/s under which the walker stands; steps a raised leg is held


class LocomotionTask(gym.Wrapper):
    """A Gymnasium MuJoCo locomotion task whose ``info`` names the body's pose (see the module docstring).

    ``seed`` seeds the first reset; ``reset(seed=s)`` restarts the sequence, as for the Meta-World tasks.
    """

    def __init__(self, task: str, seed: int = 0, render_mode: str | None = None):
        if task not in LOCOMOTION_TASKS:
            raise RatError(f"unknown locomotion task '{task}'; use one of: {', '.join(LOCOMOTION_TASKS)}")
        # the models' own "track" camera follows the body; the default free camera loses a running cheetah
        camera = {"camera_name": "track"} if render_mode is not None else {}
        super().__init__(gym.make(task, render_mode=render_mode, **camera))
        self.task, self._seed = task, seed
        model = self.env.unwrapped.model
        if render_mode is not None:
            from rat.envs.physics import fit_shadow_map

            fit_shadow_map(model, max(self.env.unwrapped.width, self.env.unwrapped.height))
        self._bodies = {model.body(i).name: i for i in range(model.nbody)}
        self._joints = {model.joint(i).name: model.jnt_qposadr[i] for i in range(model.njnt)}
        self._prev_x = self._start_x = 0.0

    def _pose(self) -> dict[str, Any]:
        data = self.env.unwrapped.data
        pose = {"x_position": float(data.qpos[self._joints["rootx"]]),
                "torso_z": float(data.xpos[self._bodies["torso"]][2]),
                "torso_pitch": float(data.qpos[self._joints["rooty"]])}
        if self.task == "Walker2d-v5":
            pose |= {"foot_z": float(data.xpos[self._bodies["foot"]][2]),
                     "foot_left_z": float(data.xpos[self._bodies["foot_left"]][2]),
                     "thigh_angle": float(data.qpos[self._joints["thigh_joint"]]),
                     "thigh_left_angle": float(data.qpos[self._joints["thigh_left_joint"]])}
        return pose

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is None and self._seed is not None:
            seed, self._seed = self._seed, None
        obs, info = self.env.reset(seed=seed, options=options)
        pose = self._pose()
        self._prev_x = self._start_x = pose["x_position"]
        return obs, {**info, **pose, "prev_x_position": self._prev_x, "start_x_position": self._start_x}

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        pose = self._pose()
        info = {**info, **pose, "prev_x_position": self._prev_x, "start_x_position": self._start_x,
                "task_reward": float(reward), "success": False}
        self._prev_x = pose["x_position"]
        return obs, reward, terminated, truncated, info


def make_locomotion(task: str, seed: int = 0, render_mode: str | None = None) -> LocomotionTask:
    """Make ``HalfCheetah-v5`` or ``Walker2d-v5`` (see :class:`LocomotionTask`)."""
    return LocomotionTask(task, seed=seed, render_mode=render_mode)


# --- target behaviours ---------------------------------------------------------------------------------


class Held:
    """A stateful success test: ``condition(info)`` holding for ``steps`` consecutive steps."""

    def __init__(self, condition, steps: int = HOLD_STEPS):
        self.condition, self.steps, self.run = condition, steps, 0

    def __call__(self, info: dict) -> bool:
        self.run = self.run + 1 if self.condition(info) else 0
        return self.run >= self.steps


def _only(task: str):
    def env_task(victim_task: str) -> str:
        if victim_task != task:
            raise RatError(f"this target behaviour is for {task} victims, not '{victim_task}'; pick another target")
        return task

    return env_task


def _backward(info: dict) -> bool:
    return info["x_position"] - info["start_x_position"] <= -BACKWARD_DISTANCE


def _pushed_up(info: dict) -> bool:
    return abs(abs(info["torso_pitch"]) - np.pi / 2) < PUSHUP_TOLERANCE


def _one_foot(info: dict) -> bool:
    right, left = info["foot_z"], info["foot_left_z"]
    standing = info["torso_z"] > UPRIGHT_Z and abs(info["x_velocity"]) < STILL_SPEED
    return standing and ((right > FOOT_UP and left < FOOT_DOWN) or (left > FOOT_UP and right < FOOT_DOWN))


def _leg_raised(info: dict) -> bool:
    raised = [(info["thigh_angle"] < THIGH_FORWARD and info["foot_z"] > LEG_UP),
              (info["thigh_left_angle"] < THIGH_FORWARD and info["foot_left_z"] > LEG_UP)]
    return info["torso_z"] > UPRIGHT_Z and any(raised)


def register_locomotion_targets() -> None:
    """Register the four locomotion target behaviours (see the module docstring)."""
    from rat.envs.targets import register_target

    register_target("cheetah-backward", success=_backward, env_task=_only("HalfCheetah-v5"),
                    description="HalfCheetah runs backwards: success once the torso is 3 m behind its start")(
        lambda obs, action, next_obs, info: -float(info["x_velocity"]))
    register_target("cheetah-pushup", success=lambda: Held(_pushed_up), stateful=True, env_task=_only("HalfCheetah-v5"),
                    description="HalfCheetah holds a push-up: torso within 20° of vertical for 20 steps")(
        lambda obs, action, next_obs, info: -abs(abs(info["torso_pitch"]) - np.pi / 2))
    register_target("walker-one-foot", success=lambda: Held(_one_foot), stateful=True, env_task=_only("Walker2d-v5"),
                    description="Walker2d stands on one foot: upright and still, one foot above 15 cm, for 20 steps")(
        lambda obs, action, next_obs, info: float(info["torso_z"] > UPRIGHT_Z)
        + abs(info["foot_z"] - info["foot_left_z"]) - abs(info["x_velocity"]))
    register_target("walker-leg-raised", success=lambda: Held(_leg_raised, LEG_HOLD_STEPS), stateful=True,
                    env_task=_only("Walker2d-v5"),
                    description="Walker2d dances with a leg raised: upright, one leg forward and its foot above "
                                "30 cm, for 100 steps")(
        lambda obs, action, next_obs, info: float(info["torso_z"] > UPRIGHT_Z) + max(info["foot_z"], info["foot_left_z"]))
