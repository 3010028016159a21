"""Physics states: what it takes to film a stored trajectory again.

An observation does not determine a MuJoCo scene (Meta-World observes the gripper, not the arm's
seven joints), so a run that will show its segments to a person records two things:

- at every step, the **physics state**: MuJoCo's full physics (time, joint positions and
  velocities, actuator activations) and the mocap poses that drive Meta-World's gripper — 28
  floats for a Meta-World task, 19 for Walker2d;
- once per episode, the **scene**: where the reset put the bodies and sites (Meta-World moves the
  object and the goal in the model itself, at every reset).

Setting both back and rendering reproduces a frame exactly (tested to the pixel, in another
instance of the environment). The frames show each state with its body positions recomputed
(``mj_forward``); the environment's own render after a step shows the positions of the step's
last sub-step start, so the two differ slightly while the body moves fast.
"""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np

from rat.errors import RatError

_SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS | mujoco.mjtState.mjSTATE_MOCAP_POS | mujoco.mjtState.mjSTATE_MOCAP_QUAT
_SCENE = ("body_pos", "body_quat", "site_pos", "site_quat")  # model fields a reset may move


def _model_data(env: gym.Env):
    inner = getattr(env, "unwrapped_metaworld", None) or env.unwrapped
    if not hasattr(inner, "model") or not hasattr(inner, "data"):
        raise RatError(f"{type(inner).__name__} is not a MuJoCo environment; only MuJoCo scenes can be filmed again")
    return inner.model, inner.data


def fit_shadow_map(model: mujoco.MjModel, frame_side: int) -> None:
    """Size ``model``'s shadow map to the frames it renders: 4× their side, a power of two, never above the model's.

    MuJoCo's default map is 4,096² whatever the frame. Rendered on the CPU (no GPU, Mesa's llvmpipe),
    that map is most of a frame's cost: measured here, a 224-pixel Meta-World frame takes 0.23 s with
    it and 0.14 s with 1,024², a 480-pixel Walker2d frame 0.12 s and 0.08 s with 2,048², the pictures
    equal to within 0.01 of 255 per pixel on average. Call before the first render (the GL context
    reads the size once).
    """
    side = 1 << max(4 * int(frame_side) - 1, 1).bit_length()
    model.vis.quality.shadowsize = min(int(model.vis.quality.shadowsize), side)


def physics_state(env: gym.Env) -> np.ndarray:
    """The full physics state of ``env`` now (float64)."""
    model, data = _model_data(env)
    state = np.empty(mujoco.mj_stateSize(model, _SPEC))
    mujoco.mj_getState(model, data, state, _SPEC)
    return state


def set_physics_state(env: gym.Env, state: np.ndarray) -> None:
    """Put ``env``'s scene in ``state`` (positions of every body recomputed; nothing is simulated)."""
    model, data = _model_data(env)
    state = np.asarray(state, dtype=np.float64)
    if state.shape != (mujoco.mj_stateSize(model, _SPEC),):
        raise RatError(f"a physics state of {state.size} floats does not fit this scene "
                       f"({mujoco.mj_stateSize(model, _SPEC)}); film states with the task that recorded them")
    mujoco.mj_setState(model, data, state, _SPEC)
    mujoco.mj_forward(model, data)


def scene(env: gym.Env) -> np.ndarray:
    """Where ``env``'s last reset put its bodies and sites (float64)."""
    model, _ = _model_data(env)
    return np.concatenate([getattr(model, name).ravel() for name in _SCENE])


def set_scene(env: gym.Env, values: np.ndarray) -> None:
    """Move ``env``'s bodies and sites to a recorded :func:`scene`."""
    model, _ = _model_data(env)
    values = np.asarray(values, dtype=np.float64)
    size = sum(getattr(model, name).size for name in _SCENE)
    if values.shape != (size,):
        raise RatError(f"a scene of {values.size} floats does not fit this task's ({size}); film scenes with the "
                       "task that recorded them")
    offset = 0
    for name in _SCENE:
        field = getattr(model, name)
        field[...] = values[offset:offset + field.size].reshape(field.shape)
        offset += field.size


def physics_of(env: gym.Env) -> tuple[np.ndarray, np.ndarray]:
    """``env``'s physics state and scene now: what :class:`~rat.preferences.segments.EpisodeHistory` keeps per step."""
    return physics_state(env), scene(env)


def render_states(env: gym.Env, states: np.ndarray, scene_values: np.ndarray | None = None) -> list[np.ndarray]:
    """One RGB frame per recorded state, in the recorded scene if given (``env`` made with
    ``render_mode="rgb_array"``)."""
    if scene_values is not None:
        set_scene(env, scene_values)
    frames = []
    for state in states:
        set_physics_state(env, state)
        frames.append(env.render())
    return frames
