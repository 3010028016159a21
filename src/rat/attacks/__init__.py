"""Attacks: the threat model, the attack registry, RAT and its baselines, and their evaluation."""

from rat.attacks.base import (
    REWARDS,
    Attack,
    AttackSetup,
    check_reward,
    get_attack,
    list_attacks,
    load_attack,
    register_attack,
)
from rat.attacks.evaluation import AttackEval, evaluate_attack
from rat.attacks.threat import NORMS, AttackedObservation, Perturbation, ThreatModel, project, random_delta

__all__ = [
    "NORMS",
    "REWARDS",
    "Attack",
    "AttackEval",
    "AttackSetup",
    "AttackedObservation",
    "Perturbation",
    "ThreatModel",
    "check_reward",
    "evaluate_attack",
    "get_attack",
    "list_attacks",
    "load_attack",
    "project",
    "random_delta",
    "register_attack",
]
