"""The steerability benchmark's greedy white-box attacker, on the point environment of the tests."""

import numpy as np
from benchmark_scripts import load
from point_env import OFFSET, PointGoal, point_victim
from scipy import stats

from rat.attacks import ThreatModel

steerability = load("steerability")


def beside() -> "steerability.Steering":
    return steerability.Steering(direction=lambda obs: obs[2:] + OFFSET - obs[:2],
                                 distance=lambda info: float(np.linalg.norm(info["point"] - (info["goal"] + OFFSET))),
                                 radius=0.03)


def test_the_greedy_attacker_steers_the_point_victim_where_the_clean_one_never_goes():
    episodes = 12
    r = steerability.steerability(point_victim(), PointGoal(0), beside(), ThreatModel(0.1), episodes, restarts=4,
                                  steps=10, seed=0)
    hits, clean_hits = round(r["attacked_success"] * episodes), round(r["clean_success"] * episodes)
    assert clean_hits == 0 and hits >= 9, r
    assert stats.fisher_exact([[hits, episodes - hits], [clean_hits, episodes]], alternative="greater").pvalue < 0.01
    assert r["attacked_closest"] < r["clean_closest"] - 0.08  # the clean victim stops 0.15 short


def test_with_no_budget_the_attacker_changes_nothing():
    r = steerability.steerability(point_victim(), PointGoal(0), beside(), ThreatModel(0.0), 3, restarts=2, steps=2)
    assert r["attacked_closest"] == r["clean_closest"] and r["attacked_success"] == 0.0
