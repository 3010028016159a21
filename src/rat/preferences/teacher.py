"""The scripted teacher of B-Pref: prefers the segment with the larger sum of target reward.

**Label convention (the one used everywhere in rat).** A label ``y`` is the probability that
the *second* segment of the pair (σ¹) is preferred: ``y = 1`` means σ¹ ≻ σ⁰, ``y = 0`` means
σ⁰ ≻ σ¹, ``y = 0.5`` means "equally good". This is B-Pref's convention (its label 1 = second
segment wins); the ``imitation`` library uses the opposite one.

Noise options (B-Pref, Lee et al. 2021):

- ``beta``: Boltzmann rationality; ``P(σ¹ ≻ σ⁰) = sigmoid(beta (R¹ − R⁰))``. ``None`` = rational.
- ``gamma``: myopia; step t of a length-L segment weighs ``gamma^(L−1−t)`` (recent steps count more).
- ``mistake``: probability of flipping a (non-equal) label.
- ``skip``: drop the query when both segments' returns are below ``skip × scale``.
- ``equal``: label 0.5 when ``|R¹ − R⁰| < equal × scale``.
- ``ties``: label 0.5 when the returns are exactly equal (a target reward that is flat or clipped
  makes many such pairs). By default, as B-Pref's teacher does, they are labelled "first segment
  preferred": noise no reward model can fit (see ``docs/notes/strength-log.md``).

``scale`` is the typical segment return (B-Pref: the mean true episode return times
``length / horizon``): the ``segment_return_scale`` of the :class:`~rat.preferences.labeller.QueryRound`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from rat.errors import RatError
from rat.preferences.labeller import Labels, QueryRound
from rat.preferences.segments import SegmentPairs


@dataclass(frozen=True)
class TeacherConfig:
    """Settings of the scripted teacher (defaults: a perfectly rational, noise-free teacher)."""

    beta: float | None = None  #: Boltzmann rationality; None = always prefer the larger return
    gamma: float = 1.0  #: myopic discount of earlier steps
    mistake: float = 0.0  #: probability of a flipped label
    skip: float = 0.0  #: skip threshold, as a fraction of the segment-return scale
    equal: float = 0.0  #: equal-preference threshold, as a fraction of the segment-return scale
    ties: bool = False  #: label exactly equal returns 0.5 (default, as B-Pref: first segment preferred)

    def __post_init__(self):
        if not 0.0 <= self.mistake <= 1.0:
            raise RatError(f"teacher mistake rate must lie in [0, 1], got {self.mistake}")
        if not 0.0 < self.gamma <= 1.0:
            raise RatError(f"teacher gamma must lie in (0, 1], got {self.gamma}")
        if self.skip < 0 or self.equal < 0 or (self.beta is not None and self.beta < 0):
            raise RatError("teacher beta, skip and equal must not be negative")


def segment_returns(reward: np.ndarray, gamma: float) -> np.ndarray:
    """Myopically discounted sums ``sum_t gamma^(L-1-t) r_t`` over the last axis."""
    length = reward.shape[-1]
    weights = gamma ** np.arange(length - 1, -1, -1, dtype=np.float64)
    return (reward * weights).sum(-1)


class ScriptedTeacher:
    """A :class:`~rat.preferences.labeller.Labeller` that labels segment pairs from their true target
    reward, with B-Pref's noise options."""

    def __init__(self, config: TeacherConfig = TeacherConfig()):
        self.config = config
        self.scale = 0.0  # of the last round answered

    def describe(self) -> dict:
        """Who labelled: JSON-able, stored with every label."""
        return {"type": "scripted", **asdict(self.config), "scale": self.scale}

    def label(self, pairs: SegmentPairs, rng: np.random.Generator, query: QueryRound | None = None) -> Labels:
        cfg = self.config
        if query is not None and np.isfinite(query.segment_return_scale):
            self.scale = float(abs(query.segment_return_scale))
        r0 = segment_returns(pairs.reward0, cfg.gamma)
        r1 = segment_returns(pairs.reward1, cfg.gamma)
        if np.isnan(r0).any() or np.isnan(r1).any():
            raise RatError("a scripted teacher needs the true target reward of every segment step")
        keep = np.arange(len(pairs))
        if cfg.skip > 0:
            keep = keep[np.maximum(r0, r1) > cfg.skip * self.scale]
        r0, r1 = r0[keep], r1[keep]
        if cfg.beta is None:
            y = (r1 > r0).astype(np.float64)
        else:
            p_second = 1.0 / (1.0 + np.exp(-cfg.beta * (r1 - r0)))
            y = (rng.random(len(keep)) < p_second).astype(np.float64)
        flip = rng.random(len(keep)) < cfg.mistake
        y[flip] = 1.0 - y[flip]
        if cfg.equal > 0:
            y[np.abs(r1 - r0) < cfg.equal * self.scale] = 0.5
        if cfg.ties:
            y[r1 == r0] = 0.5
        return Labels(keep, y)
