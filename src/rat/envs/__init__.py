"""Environments, target behaviours and success tests."""

from rat.envs.locomotion import LOCOMOTION_TASKS, LocomotionTask, make_locomotion
from rat.envs.metaworld import HORIZON, PAPER_TASKS, MetaWorldTask
from rat.envs.targets import (
    REACH_GOAL,
    REACH_RADIUS,
    TargetBehaviour,
    get_target,
    list_targets,
    opposite_task,
    register_target,
)
from rat.envs.tasks import all_tasks, check_task, make_task

__all__ = [
    "HORIZON",
    "LOCOMOTION_TASKS",
    "LocomotionTask",
    "PAPER_TASKS",
    "REACH_GOAL",
    "REACH_RADIUS",
    "MetaWorldTask",
    "TargetBehaviour",
    "all_tasks",
    "check_task",
    "get_target",
    "list_targets",
    "make_locomotion",
    "make_task",
    "opposite_task",
    "register_target",
]
