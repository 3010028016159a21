"""Environments, target behaviours and success tests."""

from rat.envs.metaworld import (
    HORIZON,
    PAPER_TASKS,
    MetaWorldTask,
    all_tasks,
    check_task,
    make_task,
)
from rat.envs.targets import (
    REACH_GOAL,
    REACH_RADIUS,
    TargetBehaviour,
    get_target,
    list_targets,
    opposite_task,
    register_target,
)

__all__ = [
    "HORIZON",
    "PAPER_TASKS",
    "REACH_GOAL",
    "REACH_RADIUS",
    "MetaWorldTask",
    "TargetBehaviour",
    "all_tasks",
    "check_task",
    "get_target",
    "list_targets",
    "make_task",
    "opposite_task",
    "register_target",
]
