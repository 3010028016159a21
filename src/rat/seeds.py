"""Where every evaluation draws its episodes, named once.

Training draws its own episodes from the run's generator. Evaluations must not share them, and
two evaluations of the same kind must see the same episodes (so a kept snapshot and the last
adversary, or an attacked and a clean victim, are compared on equal terms). Each kind of
evaluation therefore resets its environments from a fixed offset:

=====================  =====================================  ===================================
evaluation             environment made with seed             episode ``i`` reset with seed
=====================  =====================================  ===================================
periodic, at step t    ``run seed + EVAL_ENV``                ``PERIODIC + t + i``
final                  ``run seed + EVAL_ENV`` (attacks),     ``FINAL + i``
                       ``run seed + FRESH_ENV`` (policies)
selection by r̂         ``run seed + SELECTION_ENV``           ``SELECTION + i``
reward quality         ``run seed + FRESH_ENV``               ``SELECTION + i``
=====================  =====================================  ===================================

Victim training keeps its own offsets (:data:`VICTIM_EVAL_ENV`, :data:`VICTIM_PERIODIC`), which
its shipped victims were made with.
"""

EVAL_ENV = 7  #: added to the run's seed for the environment of attack and intention evaluations
FRESH_ENV = 1  #: added to the run's seed for a final evaluation on environments never trained on
SELECTION_ENV = 11  #: added to the run's seed for scoring adversary snapshots with r̂
ROBUST = 13  #: added to the run's seed for a robust agent's environment and generator (its episodes, batches)

PERIODIC = 10**7  #: + step: first episode seed of the evaluation at that step
FINAL = 2 * 10**7  #: first episode seed of final evaluations
SELECTION = 3 * 10**7  #: first episode seed of snapshot selection and reward-quality rollouts

VICTIM_EVAL_ENV = 10**6  #: added to the seed for a victim's periodic evaluations (and their episodes, + step)
VICTIM_FINAL = 10**6  #: + seed: first episode of a victim's final evaluation


def periodic(step: int) -> int:
    """First episode seed of the periodic evaluation at environment ``step``."""
    return PERIODIC + step
