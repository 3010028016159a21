"""Robust training against targeted attacks: RAT-ATLA, RAT-WocaR, ATLA and PA-ATLA with SAC agents.

    from rat.robust import RobustConfig, train_robust

    report = train_robust(RobustConfig(method="rat-atla"), victim, target, make_env, ThreatModel(0.1), "runs/robust",
                          adversary_config=rat_config("cpu", budget=3000, target="reach"))

The trainer (:class:`RobustTrainer`) alternates the agent's and the adversary's phases on the project's
training loop; the adversaries are the attacks' own trainers, stepped (:mod:`rat.robust.adversaries`);
RAT-WocaR's worst-case terms are in :mod:`rat.robust.terms`. ``docs/robust.md`` says what each method does
and where it departs from the originals.
"""

from rat.robust.adversaries import PhaseAdversary, PPOAdversary, RATAdversary
from rat.robust.run import evaluate_robust, prepare_robust, train_robust
from rat.robust.trainer import ADVERSARY_OF, METHODS, RobustConfig, RobustTrainer

__all__ = ["ADVERSARY_OF", "METHODS", "PPOAdversary", "PhaseAdversary", "RATAdversary", "RobustConfig",
           "RobustTrainer", "evaluate_robust", "prepare_robust", "train_robust"]
