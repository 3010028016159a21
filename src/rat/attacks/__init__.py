"""Attacks: the threat model, RAT, and (later) its baselines."""

from rat.attacks.rat import (
    ABLATIONS,
    AttackEval,
    CombinedBehaviourPolicy,
    RATConfig,
    evaluate_attack,
    load_adversary,
    train_rat,
)
from rat.attacks.threat import NORMS, AttackedObservation, perturb, project, random_delta

__all__ = [
    "ABLATIONS",
    "NORMS",
    "AttackEval",
    "AttackedObservation",
    "CombinedBehaviourPolicy",
    "RATConfig",
    "evaluate_attack",
    "load_adversary",
    "perturb",
    "project",
    "random_delta",
    "train_rat",
]
