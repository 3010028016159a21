"""Preference learning: segments, query strategies, scripted teachers, the reward ensemble,
the label store, and PEBBLE training of the intention policy."""

from rat.preferences.labeller import Labeller, Labels, QueryRound
from rat.preferences.pebble import PebbleConfig, PebbleLearner
from rat.preferences.queries import STRATEGIES, select_queries
from rat.preferences.reward_model import RewardEnsemble, RewardModelConfig, bradley_terry_loss
from rat.preferences.schedule import FeedbackSchedule
from rat.preferences.segments import EpisodeHistory, SegmentPairs
from rat.preferences.store import LabelSet, LabelStore
from rat.preferences.teacher import ScriptedTeacher, TeacherConfig

__all__ = [
    "STRATEGIES",
    "EpisodeHistory",
    "FeedbackSchedule",
    "LabelSet",
    "LabelStore",
    "Labeller",
    "Labels",
    "PebbleConfig",
    "PebbleLearner",
    "QueryRound",
    "RewardEnsemble",
    "RewardModelConfig",
    "ScriptedTeacher",
    "SegmentPairs",
    "TeacherConfig",
    "bradley_terry_loss",
    "select_queries",
]
