"""The steerability benchmark's greedy white-box attacker, on the point environment of the tests."""

import numpy as np
import pytest
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


def test_the_probe_is_a_registered_attack_that_steers_the_point_victim(tmp_path):
    from point_env import BESIDE

    from rat.attacks import AttackSetup, get_attack, load_attack
    from rat.attacks.probe import ProbeConfig, register_steering
    from rat.errors import RatError

    register_steering("beside", lambda obs: obs[2:] + OFFSET - obs[:2])
    setup = AttackSetup(point_victim(), BESIDE, PointGoal, ThreatModel(0.1), seed=0, reward="none", progress=False)
    report = get_attack("probe").train(setup, ProbeConfig(restarts=4, steps=10, final_eval_episodes=20), tmp_path / "run")
    hits, clean = round(report.attack_success_rate * 20), round(report.clean_success_rate * 20)
    assert hits >= 14 and clean == 0 and report.max_perturbation <= 0.1 + 1e-9, report.summary()
    assert stats.fisher_exact([[hits, 20 - hits], [clean, 20]], alternative="greater").pvalue < 0.01
    delta, meta = load_attack(tmp_path / "run", point_victim())
    assert meta["method"] == "probe" and np.abs(delta(np.array([0.0, 0.0, 0.2, 0.0]))).max() <= 1 + 1e-6
    unsteered = AttackSetup(point_victim(), BESIDE.__class__(**{**BESIDE.__dict__, "name": "nowhere"}), PointGoal,
                            ThreatModel(0.1), reward="none", progress=False)
    with pytest.raises(RatError, match="the probe needs to know which way target 'nowhere' lies"):
        get_attack("probe").train(unsteered, ProbeConfig(), tmp_path / "other")
    assert not (tmp_path / "other").exists()
