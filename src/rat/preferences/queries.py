"""Query selection: which of many candidate segment pairs to ask the teacher about.

Strategies (B-Pref's, by name):

- ``uniform``: uniformly at random;
- ``disagreement``: largest standard deviation of the members' P[σ¹ ≻ σ⁰];
- ``entropy``: largest mean (over members) entropy of P[σ¹ ≻ σ⁰];
- ``kcenter``: greedy k-center in segment space, away from pairs already labelled;
- ``kcenter-disagreement`` / ``kcenter-entropy``: the top half of the candidates by
  disagreement / entropy, then greedy k-center among them.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from rat.errors import RatError
from rat.preferences.reward_model import RewardEnsemble
from rat.preferences.segments import SegmentPairs


def pair_features(pairs: SegmentPairs) -> np.ndarray:
    """Each pair flattened to one vector (both segments' observations and actions)."""
    n = len(pairs)
    return np.concatenate([pairs.obs0.reshape(n, -1), pairs.act0.reshape(n, -1),
                           pairs.obs1.reshape(n, -1), pairs.act1.reshape(n, -1)], axis=1).astype(np.float32)


def disagreement(ensemble: RewardEnsemble, pairs: SegmentPairs) -> np.ndarray:
    """Standard deviation over members of P[σ¹ ≻ σ⁰], per pair."""
    return ensemble.preference_probabilities(pairs.obs0, pairs.act0, pairs.obs1, pairs.act1).std(0)


def entropy(ensemble: RewardEnsemble, pairs: SegmentPairs) -> np.ndarray:
    """Mean over members of the binary entropy of P[σ¹ ≻ σ⁰], per pair."""
    p = np.clip(ensemble.preference_probabilities(pairs.obs0, pairs.act0, pairs.obs1, pairs.act1), 1e-7, 1 - 1e-7)
    return (-(p * np.log(p) + (1 - p) * np.log(1 - p))).mean(0)


def kcenter_greedy(features: np.ndarray, n: int, centres: np.ndarray | None = None) -> np.ndarray:
    """Pick ``n`` rows of ``features``, each the farthest from the centres chosen so far
    (``centres``: rows already covered, e.g. labelled pairs)."""
    import torch

    x = torch.as_tensor(features)
    if centres is not None and len(centres):
        dist = torch.cdist(x, torch.as_tensor(centres)).min(1).values
    else:
        dist = torch.full((len(x),), float("inf"))
    chosen = []
    for _ in range(min(n, len(x))):
        i = int(torch.argmax(dist))
        chosen.append(i)
        dist = torch.minimum(dist, torch.cdist(x, x[i:i + 1]).squeeze(1))
        dist[i] = -1.0
    return np.asarray(chosen)


def _top(scores: np.ndarray, n: int) -> np.ndarray:
    return np.argsort(-scores, kind="stable")[:n]


def _kcenter_after(score: Callable) -> Callable:
    def select(candidates, n, ensemble, rng, labelled):
        half = _top(score(ensemble, candidates), max(n, len(candidates) // 2))
        pick = kcenter_greedy(pair_features(candidates.select(half)), n, labelled)
        return half[pick]

    return select


STRATEGIES: dict[str, Callable] = {
    "uniform": lambda c, n, e, rng, labelled: rng.choice(len(c), size=min(n, len(c)), replace=False),
    "disagreement": lambda c, n, e, rng, labelled: _top(disagreement(e, c), n),
    "entropy": lambda c, n, e, rng, labelled: _top(entropy(e, c), n),
    "kcenter": lambda c, n, e, rng, labelled: kcenter_greedy(pair_features(c), n, labelled),
    "kcenter-disagreement": _kcenter_after(disagreement),
    "kcenter-entropy": _kcenter_after(entropy),
}


def select_queries(strategy: str, candidates: SegmentPairs, n: int, ensemble: RewardEnsemble,
                   rng: np.random.Generator, labelled: np.ndarray | None = None) -> np.ndarray:
    """Indices of the ``n`` candidates to ask about.

    Args:
        strategy: one of :data:`STRATEGIES`.
        labelled: :func:`pair_features` of pairs already labelled (k-center strategies only).
    """
    if strategy not in STRATEGIES:
        raise RatError(f"unknown query strategy '{strategy}'; use one of: {', '.join(STRATEGIES)}")
    return np.asarray(STRATEGIES[strategy](candidates, n, ensemble, rng, labelled), dtype=np.int64)
