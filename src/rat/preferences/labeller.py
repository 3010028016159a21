"""Who answers preference queries: the :class:`Labeller` protocol.

PEBBLE (and so RAT) asks a labeller to compare pairs of trajectory segments once per query
round. Anything with ``label`` and ``describe`` can answer: the scripted teacher of B-Pref
(:class:`~rat.preferences.teacher.ScriptedTeacher`), a person behind a labelling page, a
model. Labels follow the one convention of :mod:`rat.preferences.teacher`: ``y`` is the
probability that the *second* segment is preferred (1, 0, or 0.5 for "equally good"); a query
left out of the answer's ``index`` was skipped.

Two optional attributes change what the learner does around a labeller:

- ``films_segments = True``: the run records every step's physics state (:mod:`rat.envs.physics`),
  and the pairs a labeller gets carry it (``SegmentPairs.physics``), to be filmed;
- ``stores_labels = True``: the labeller writes each answer into the run's label store itself, as
  it is given (:meth:`~rat.preferences.store.LabelStore.answer`), and closes the round; the learner
  then stores nothing for it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from rat.preferences.segments import SegmentPairs


@dataclass(frozen=True)
class QueryRound:
    """What a labeller is told about the round its queries come from.

    Attributes:
        round: the round's index in its run (0 is the first).
        step: the environment step at which the run asks.
        source: the run that asks (its name in the label store).
        task, target: the environment task and the target behaviour, where known.
        segment_return_scale: the mean true target return of a segment in the recent episodes
            (the scale of B-Pref's skip and equal thresholds); NaN where no true reward is known.
    """

    round: int
    step: int
    source: str
    task: str | None = None
    target: str | None = None
    segment_return_scale: float = float("nan")


@dataclass
class Labels:
    """The answered queries: ``index`` into the pairs asked, and the label ``y`` of each."""

    index: np.ndarray  # [m] int
    y: np.ndarray  # [m] float: P[second segment preferred]


@runtime_checkable
class Labeller(Protocol):
    """Answers preference queries (see the module docstring for the label convention)."""

    def label(self, pairs: SegmentPairs, rng: np.random.Generator, query: QueryRound) -> Labels:
        """Labels for ``pairs`` (``pairs.reward0/1`` hold the true target reward where it is known)."""

    def describe(self) -> dict[str, Any]:
        """Who labelled, JSON-able, with a ``"type"`` key (``"scripted"``, ``"human"``, ...); stored with every label."""
