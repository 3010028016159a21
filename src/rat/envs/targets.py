"""Target behaviours: what the attacker wants the victim to do.

A target behaviour is a named pair (target reward, success test). The attack itself never sees
the target reward: it learns from preference labels. The target reward is what a *scripted*
teacher uses to label, and what evaluation and the "oracle" baselines use.

Both functions read one transition and the environment's ``info`` (see
:mod:`rat.envs.metaworld` for its keys)::

    reward(obs, action, next_obs, info) -> float
    success(info) -> bool

An episode succeeds if the success test holds at *any* step. A test that needs the episode so
far ("above z = 0.30 for 20 consecutive steps") is registered with ``stateful=True``: its
``success`` is then a factory called at every episode start, returning that episode's test::

    class HeldHigh:
        def __init__(self):
            self.run = 0

        def __call__(self, info):
            self.run = self.run + 1 if info["tcp_pos"][2] > 0.30 else 0
            return self.run >= 20

    register_target("hold-high", success=HeldHigh, stateful=True)(lift_gripper)

Whoever runs episodes asks :meth:`TargetBehaviour.episode_success` for a fresh test per episode.

Register your own behaviour with :func:`register_target`::

    from rat.envs import register_target

    @register_target("lift-gripper", success=lambda info: info["tcp_pos"][2] > 0.3,
                     description="raise the gripper above 30 cm")
    def lift_gripper(obs, action, next_obs, info):
        return 10.0 * (info["tcp_pos"][2] - info["prev_tcp_pos"][2])
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rat.envs.metaworld import PAPER_TASKS
from rat.errors import RatError
from rat.plugins import Registry

RewardFn = Callable[[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]], float]
SuccessFn = Callable[[dict[str, Any]], bool]


def _same_task(victim_task: str) -> str:
    return victim_task


@dataclass(frozen=True)
class TargetBehaviour:
    """A behaviour the attacker wants, with the environment it is sought in.

    Attributes:
        name: registry name.
        description: one sentence for listings.
        reward: target reward of a transition (see module docstring).
        success: success test on a step's ``info``.
        env_task: maps the victim's task to the task whose environment the attack runs in
            (identity for the manipulation scenario, the opposite task for opposite behaviours).
        stateful: ``success`` is a factory of per-episode tests (see the module docstring).
    """

    name: str
    description: str
    reward: RewardFn
    success: SuccessFn | Callable[[], SuccessFn]
    env_task: Callable[[str], str] = field(default=_same_task)
    stateful: bool = False

    def episode_success(self) -> SuccessFn:
        """The success test of one new episode: call it on every step's ``info``, in order."""
        return self.success() if self.stateful else self.success


_REGISTRY: Registry[TargetBehaviour] = Registry("target behaviour", "rat list targets")


def register_target(
    name: str,
    *,
    success: SuccessFn,
    description: str = "",
    env_task: Callable[[str], str] = _same_task,
    stateful: bool = False,
    overwrite: bool = False,
) -> Callable[[RewardFn], RewardFn]:
    """Decorator that registers ``reward`` as the target behaviour ``name``.

    ``success`` is a test of one step's ``info``, or, with ``stateful=True``, a factory of
    per-episode tests that may keep state across the episode's steps.
    """

    def decorate(reward: RewardFn) -> RewardFn:
        _REGISTRY.add(name, TargetBehaviour(name, description or (reward.__doc__ or "").strip(), reward, success,
                                            env_task, stateful), overwrite)
        return reward

    return decorate


def get_target(name: str) -> TargetBehaviour:
    """Look a target behaviour up by name."""
    return _REGISTRY.get(name)


def list_targets() -> list[TargetBehaviour]:
    """All registered target behaviours, sorted by name."""
    return _REGISTRY.all()


# --- the manipulation scenario -------------------------------------------------------------

#: Where the manipulation scenario wants the gripper (metres, Meta-World world frame).
REACH_GOAL = np.array([0.45, 0.70, 0.25])
#: Success radius of the manipulation scenario (the paper's table; the released code used 0.08).
REACH_RADIUS = 0.05


def _long_tail_tolerance(distance: float, bound: float, margin: float) -> float:
    """Meta-World's ``tolerance(x, bounds=(0, bound), margin, sigmoid='long_tail')``, value 0.1 at the margin."""
    if distance <= bound:
        return 1.0
    if margin <= 0.0:
        return 0.0
    scale = np.sqrt(1.0 / 0.1 - 1.0)  # long_tail: 1 / ((x * scale)^2 + 1), equal to 0.1 at x = 1
    x = (distance - bound) / margin
    return float(1.0 / ((x * scale) ** 2 + 1.0))


def reach_reward(obs: np.ndarray, action: np.ndarray, next_obs: np.ndarray, info: dict[str, Any]) -> float:
    """Gripper to (0.45, 0.70, 0.25): 10 x this step's progress, plus a tolerance bonus within 0.1 m.

    The shaping follows the released RAT code: progress is the decrease of the tool centre
    point's distance to the goal during the step; within 0.1 m a long-tail tolerance bonus
    (bounds (0, 0.05), margin = the episode's initial distance) is added.
    """
    before = float(np.linalg.norm(info["prev_tcp_pos"] - REACH_GOAL))
    after = float(np.linalg.norm(info["tcp_pos"] - REACH_GOAL))
    reward = 10.0 * (before - after)
    if after < 0.1:
        margin = float(np.linalg.norm(info["tcp_init"] - REACH_GOAL))
        reward += _long_tail_tolerance(after, 0.05, margin)
    return reward


def reach_success(info: dict[str, Any]) -> bool:
    """Tool centre point within 5 cm of the manipulation goal."""
    return bool(np.linalg.norm(info["tcp_pos"] - REACH_GOAL) < REACH_RADIUS)


register_target(
    "reach",
    success=reach_success,
    description="manipulation scenario: bring the gripper to (0.45, 0.70, 0.25), success within 5 cm",
)(reach_reward)


# --- the opposite-behaviour scenario ---------------------------------------------------------


def opposite_task(victim_task: str) -> str:
    """The opposite of one of the paper's eight tasks (open <-> close, lock <-> unlock)."""
    if victim_task not in PAPER_TASKS:
        raise RatError(
            f"task '{victim_task}' has no opposite behaviour; use one of: {', '.join(sorted(PAPER_TASKS))}"
        )
    return PAPER_TASKS[victim_task]


def task_reward(obs: np.ndarray, action: np.ndarray, next_obs: np.ndarray, info: dict[str, Any]) -> float:
    """The environment's own task reward."""
    return float(info["task_reward"])


def task_success(info: dict[str, Any]) -> bool:
    """The environment's own success test."""
    return bool(info["success"])


register_target(
    "opposite",
    success=task_success,
    env_task=opposite_task,
    description="opposite-behaviour scenario: run in the opposite task (open<->close, lock<->unlock) "
    "and do it; that task's own reward and success",
)(task_reward)

register_target(
    "task",
    success=task_success,
    description="the victim's own task (its own reward and success): what a clean victim already does",
)(task_reward)


from rat.envs.locomotion import register_locomotion_targets  # noqa: E402 - needs register_target above

register_locomotion_targets()
