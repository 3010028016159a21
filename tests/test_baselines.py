"""The baselines: their adversary MDPs, the PA-AD actor, learning on the point environment, label sets."""

import csv
import json
import multiprocessing
import sys
import time

import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from point_env import BESIDE, PointGoal, point_victim
from scipy import stats

from rat.attacks import AttackSetup, ThreatModel, evaluate_attack, get_attack, load_attack
from rat.attacks.gradient import directed_perturbation, mad_perturbation
from rat.attacks.rl import DirectorEnv, PPOConfig, StateAdversaryEnv
from rat.attacks.simple import SimpleConfig
from rat.attacks.threat import perturbation_norm, random_delta
from rat.envs import get_target, make_task
from rat.errors import RatError
from rat.preferences.offline import learn_reward, reward_source
from rat.preferences.segments import SegmentPairs
from rat.preferences.store import LabelStore
from rat.victims import load_victim


def train_baseline(method, victim, target, make_env, out, epsilon=0.1, ppo=None, labels=None, seed=0, reward=None):
    """Train a registered baseline against ``victim`` (oracle unless given labels)."""
    attack = get_attack(method)
    reward = reward or ("labels" if labels is not None else ("oracle" if "oracle" in attack.rewards else "none"))
    setup = AttackSetup(victim, target, make_env, ThreatModel(epsilon), seed, reward, labels, progress=False)
    config = (ppo or PPOConfig()) if attack.config is PPOConfig else SimpleConfig()
    return attack.train(setup, config, out)


EPS = 0.1


@pytest.fixture(scope="module")
def zoo_victim():
    # The behaviour clone: its actions respond to ε-sized changes everywhere, which these actor tests need
    # (the SAC victim saturates, so a one-step FGSM from a random start often cannot move it at all).
    return load_victim("zoo:drawer-open-v3@bc")


@pytest.mark.filterwarnings("ignore:.*Box observation space (minimum|maximum) value is")  # Meta-World's ±inf bounds
def test_the_sa_rl_environment_passes_gymnasiums_checker_and_stays_in_the_ball(zoo_victim):
    target = get_target("reach")
    for norm in ("linf", "l2", "l1"):
        env = StateAdversaryEnv(make_task("drawer-open-v3", seed=0), zoo_victim, target.reward, target,
                                ThreatModel(EPS, norm))
        check_env(env, skip_render_check=True)
        env.reset(seed=1)
        rng = np.random.default_rng(0)
        for _ in range(30):
            action = rng.uniform(-3, 3, env.action_space.shape)  # beyond the space too: a PPO may emit anything
            *_, info = env.step(action)
            assert perturbation_norm(info["perturbation"], norm) <= EPS + 1e-6
        env.close()
    director = DirectorEnv(make_task("drawer-open-v3", seed=0), zoo_victim, target.reward, target, ThreatModel(EPS))
    check_env(director, skip_render_check=True)
    director.reset(seed=2)
    for _ in range(10):
        *_, info = director.step(director.action_space.sample())
        assert np.abs(info["perturbation"]).max() <= EPS + 1e-6
    director.close()


def test_the_pa_ad_actor_moves_the_victims_action_along_the_direction_inside_the_ball(zoo_victim):
    env = make_task("drawer-open-v3", seed=0)
    obs = [env.reset(seed=s)[0] for s in range(8)]
    env.action_space.seed(0)
    for _ in range(120):  # states of real episodes, random directions
        obs.append(env.step(env.action_space.sample())[0])
    env.close()
    s = torch.as_tensor(np.stack(obs), dtype=torch.float32)
    rng = np.random.default_rng(0)
    for norm in ("linf", "l2", "l1"):
        for steps in (1, 10):  # FGSM from a random start (the paper's), PGD
            direction = torch.as_tensor(rng.standard_normal((len(s), 4)), dtype=torch.float32)
            delta = directed_perturbation(zoo_victim, s, direction, ThreatModel(EPS, norm), steps=steps, generator=rng)
            assert (perturbation_norm((EPS * delta).numpy(), norm) <= EPS + 1e-6).all()
            with torch.no_grad():
                change = zoo_victim.act(s + EPS * delta) - zoo_victim.act(s)
            cosine = torch.nn.functional.cosine_similarity(change, direction, dim=-1).numpy()
            # λ‖change‖ trades some alignment for size, and the victim saturates: positive on average,
            # significantly so, and mostly positive once PGD searches the ball.
            assert stats.ttest_1samp(cosine, 0.0, alternative="greater").pvalue < 0.01, f"{norm}, {steps} steps"
            assert steps == 1 or (cosine > 0).mean() > 2 / 3, f"{norm}, {steps} steps: {(cosine > 0).mean():.2f}"
    mad = mad_perturbation(zoo_victim, s, ThreatModel(EPS), generator=rng)
    with torch.no_grad():
        mad_change = (zoo_victim.act(s + EPS * mad) - zoo_victim.act(s)).norm(dim=-1)
        random_change = (zoo_victim.act(s + EPS * torch.as_tensor(
            np.stack([random_delta(rng, s.shape[1], "linf") for _ in s]), dtype=torch.float32)) - zoo_victim.act(s)).norm(dim=-1)
    assert (mad_change > random_change).float().mean() > 0.9


def small_ppo(steps):
    return PPOConfig(total_steps=steps, learning_rate=1e-3, batch_size=100, n_steps=400, hidden=64, layers=2,
                     target_kl=0.05, eval_every=4000, eval_episodes=10, final_eval_episodes=50)


@pytest.mark.slow
@pytest.mark.parametrize("method, steps", [("sa-rl", 16000), ("pa-ad", 8000)])
def test_oracle_baselines_beat_a_random_attack_on_the_point_environment(tmp_path, method, steps):
    report = train_baseline(method, point_victim(), BESIDE, PointGoal, tmp_path / method, EPS, ppo=small_ppo(steps))
    random = train_baseline("random", point_victim(), BESIDE, PointGoal, tmp_path / "random", EPS, ppo=small_ppo(steps))
    hits, rnd = round(report.attack_success_rate * 50), round(random.attack_success_rate * 50)
    p = stats.fisher_exact([[hits, 50 - hits], [rnd, 50 - rnd]], alternative="greater").pvalue
    assert hits / 50 >= 0.15 and p < 0.01, f"{method} {hits}/50, random {rnd}/50, p={p:.2g}"
    assert report.reward == "oracle" and report.max_perturbation <= EPS + 1e-9
    assert report.clean_success_rate is not None and report.clean_success_rate < report.attack_success_rate
    with open(tmp_path / method / "metrics.csv") as f:
        evals = [row["eval_success_rate"] for row in csv.DictReader(f) if row.get("eval_success_rate")]
    assert len(evals) == steps // 4000 and report.details["ppo_updates"] > 50  # PPO's updates ran and were evaluated
    attack, meta = load_attack(tmp_path / method, point_victim())  # and the saved attack is the trained one
    again = evaluate_attack(point_victim(), attack, PointGoal(7), BESIDE, ThreatModel(EPS), 50, seed=2 * 10**7)
    assert meta["method"] == method and abs(again.result.success_rate - report.attack_success_rate) < 0.15


def labelled_store(path, n, source="rat-run", seed=0):
    """A store of ``n`` scripted labels of the point environment's target reward."""
    rng = np.random.default_rng(seed)
    obs0, obs1 = rng.uniform(-0.5, 0.5, (2, n, 5, 4)).astype(np.float32)
    act0, act1 = rng.uniform(-1, 1, (2, n, 5, 2)).astype(np.float32)
    r0, r1 = -np.abs(obs0[..., 0]).sum(-1), -np.abs(obs1[..., 0]).sum(-1)  # prefer x near 0
    pairs = SegmentPairs(obs0, act0, r0[:, None].repeat(5, 1), obs1, act1, r1[:, None].repeat(5, 1))
    with LabelStore(path) as store:
        return store.add(pairs, (r1 > r0).astype(float), {"type": "scripted"}, source=source, round=0)


@pytest.mark.slow
def test_a_baseline_given_a_label_set_reads_exactly_those_labels(tmp_path):
    ids = labelled_store(tmp_path / "labels.sqlite", 60)
    ensemble, metrics = learn_reward(tmp_path / "labels.sqlite", 4, 2, seed=0)
    assert metrics["labels"] == 60 and metrics["label_ids"] == ids
    assert metrics["reward_train_accuracy"] > 0.9  # it learnt the labels' preference (x near 0)
    r = reward_source(BESIDE, ensemble)
    assert r(np.zeros(4), np.zeros(2), None, {}) > r(np.array([0.5, 0, 0, 0]), np.zeros(2), None, {})
    report = train_baseline("sa-rl", point_victim(), BESIDE, PointGoal, tmp_path / "run", EPS, ppo=small_ppo(800),
                            labels=tmp_path / "labels.sqlite")
    assert report.reward == "labels" and report.labels == 60
    assert json.loads((tmp_path / "run" / "labels_used.json").read_text()) == ids


@pytest.mark.slow
def test_the_learned_reward_is_kept_beside_its_label_store_and_relearnt_when_the_labels_change(tmp_path, monkeypatch):
    from rat.preferences.reward_model import RewardEnsemble

    store = tmp_path / "labels.sqlite"
    labelled_store(store, 30)
    first, metrics = learn_reward(store, 4, 2, seed=0, cache=True)
    rounds = []
    train_round = RewardEnsemble.train_round
    monkeypatch.setattr(RewardEnsemble, "train_round", lambda self, *a: rounds.append(1) or train_round(self, *a))
    again, kept = learn_reward(store, 4, 2, seed=0, cache=True)
    assert rounds == [] and kept == metrics  # reused, not retrained
    x, a = np.random.default_rng(0).normal(size=(8, 4)), np.zeros((8, 2))
    np.testing.assert_array_equal(first.r_hat(x, a), again.r_hat(x, a))
    learn_reward(store, 4, 2, seed=1, cache=True)  # another seed is another model
    labelled_store(store, 10, source="later")
    _, grown = learn_reward(store, 4, 2, seed=0, cache=True)
    assert rounds == [1, 1] and grown["labels"] == 40
    (tmp_path / "labels-reward-seed0.safetensors").write_bytes(b"garbage")
    learn_reward(store, 4, 2, seed=0, cache=True)  # a damaged copy is learnt again, not trusted
    assert rounds == [1, 1, 1]


def _learn_cached(store, rounds):
    from rat.preferences.reward_model import RewardEnsemble

    train_round = RewardEnsemble.train_round

    def counted(self, *a):
        with rounds.get_lock():
            rounds.value += 1
        time.sleep(1.0)  # long enough for the other process to reach the cache while this one learns
        return train_round(self, *a)

    RewardEnsemble.train_round = counted
    learn_reward(store, 4, 2, seed=0, cache=True)


@pytest.mark.slow
@pytest.mark.skipif(sys.platform == "win32", reason="fork and fcntl are POSIX")
def test_two_processes_wanting_the_same_uncached_reward_learn_it_once(tmp_path):
    store = tmp_path / "labels.sqlite"
    labelled_store(store, 30)
    fork = multiprocessing.get_context("fork")
    rounds = fork.Value("i", 0)
    workers = [fork.Process(target=_learn_cached, args=(store, rounds)) for _ in range(2)]
    for w in workers:
        w.start()
    for w in workers:
        w.join(timeout=120)
        w.kill()  # a worker still waiting after two minutes is a failure below, not a leftover process
    assert [w.exitcode for w in workers] == [0, 0]
    assert rounds.value == 1  # the second waited on the lock and read the first's ensemble
    assert (tmp_path / "labels-reward-seed0.json").exists()


def test_baselines_refuse_bad_input_in_one_line(tmp_path):
    with pytest.raises(RatError, match="no label store"):
        train_baseline("pa-ad", point_victim(), BESIDE, PointGoal, tmp_path / "a", labels=tmp_path / "none.sqlite")
    with pytest.raises(RatError, match="unknown attack 'fgsm'"):
        train_baseline("fgsm", point_victim(), BESIDE, PointGoal, tmp_path / "b")
    with pytest.raises(RatError, match="learns from none, not 'labels'"):
        train_baseline("random", point_victim(), BESIDE, PointGoal, tmp_path / "c", labels=tmp_path / "x")
    with pytest.raises(RatError, match="give --labels STORE"):
        train_baseline("sa-rl", point_victim(), BESIDE, PointGoal, tmp_path / "d", reward="labels")
    labelled_store(tmp_path / "labels.sqlite", 4)
    with pytest.raises(RatError, match="labels in .* are for observations 4-d"):
        learn_reward(tmp_path / "labels.sqlite", 39, 4)
    with pytest.raises(RatError, match="must be positive"):
        PPOConfig(total_steps=-1)
    assert not any((tmp_path / name).exists() for name in "abcd")
