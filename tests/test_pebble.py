"""The PEBBLE learner driven by a small environment shipped with the tests."""

import numpy as np
import pytest

from rat.agents.sac import SACConfig
from rat.preferences.pebble import PebbleConfig, PebbleLearner, updates_due
from rat.preferences.reward_model import RewardModelConfig
from rat.preferences.store import LabelStore


class Drift:
    """A point in the plane moved by the action; episodes of 60 steps; target reward = x-progress."""

    def __init__(self, rng):
        self.rng, self.t = rng, 0

    def reset(self):
        self.x, self.t = self.rng.uniform(-1, 1, 2).astype(np.float32), 0
        return self.x.copy()

    def step(self, a):
        prev = self.x.copy()
        self.x = np.clip(self.x + 0.1 * np.asarray(a[:2]), -2, 2).astype(np.float32)
        self.t += 1
        return self.x.copy(), float(self.x[0] - prev[0]), self.t >= 60


def tiny_config(**kw):
    base = dict(sac=SACConfig(hidden=32, layers=2, batch_size=64, lr=1e-3), seed_steps=60, unsupervised_steps=180,
                budget=70, per_round=30, feedback_every=120, segment_length=10, candidates_factor=4,
                reward=RewardModelConfig(hidden=32, layers=2, max_epochs=5), reset_updates=10, buffer_capacity=5000)
    base.update(kw)
    return PebbleConfig(**base)


def drive(learner, env, steps, interrupt_at=None):
    obs = env.reset()
    while learner.step < steps:
        action = learner.act(obs)
        next_obs, r, end = env.step(action)
        learner.observe(obs, action, next_obs, r, terminated=False, truncated=end)
        obs = env.reset() if end else next_obs
        if interrupt_at is not None and learner.step == interrupt_at:
            return


def make(tmp_path, config, name="run"):
    rng = np.random.default_rng(0)
    store = LabelStore(tmp_path / "labels.sqlite")
    return PebbleLearner(2, 2, config, store, name, rng), Drift(np.random.default_rng(1))


@pytest.mark.slow
def test_budget_is_spent_exactly_and_recorded_round_by_round(tmp_path):
    learner, env = make(tmp_path, tiny_config())
    drive(learner, env, 700)
    rounds = learner.store.rounds("run")
    assert learner.asked == 70 and sum(r["asked"] for r in rounds) == 70
    assert [(r["step"], r["asked"]) for r in rounds] == [(240, 30), (360, 30), (480, 10)]
    assert learner.store.count("run") == sum(r["answered"] for r in rounds) == 70


def test_after_a_round_every_stored_reward_is_the_learned_reward_and_the_critic_was_reset(tmp_path):
    learner, env = make(tmp_path, tiny_config(budget=30))
    drive(learner, env, 239)
    critic_before = learner.agent.critic
    assert np.all(learner.buffer.reward[: len(learner.buffer)] == 0.0)  # no r̂ before the first round
    drive(learner, env, 240)  # the first query round happens at step 240
    assert learner.agent.critic is not critic_before  # reset
    assert learner.ensemble.rounds == 1 and learner.agent.updates > 180
    n = len(learner.buffer)
    np.testing.assert_allclose(learner.buffer.reward[:n], learner.ensemble.r_hat(learner.buffer.obs[:n],
                                                                                  learner.buffer.action[:n]), rtol=1e-5)


def test_each_round_logs_how_r_hat_agrees_with_the_targets_reward_over_recent_episodes(tmp_path):
    learner, env = make(tmp_path, tiny_config(budget=30))
    obs = env.reset()
    for _ in range(240):  # the first round comes at step 240, as the fourth 60-step episode ends
        action = learner.act(obs)
        next_obs, r, end = env.step(action)
        metrics = learner.observe(obs, action, next_obs, r, terminated=False, truncated=end)
        obs = env.reset() if end else next_obs
    episodes = list(learner.history.episodes)
    assert len(episodes) == 4 and {"reward_step_corr", "reward_segment_corr", "reward_pairs_ordered"} <= set(metrics)
    learned = np.concatenate([learner.ensemble.r_hat(o, a) for o, a, _ in episodes])
    true = np.concatenate([t for _, _, t in episodes])
    assert metrics["reward_step_corr"] == pytest.approx(np.corrcoef(learned, true)[0, 1], abs=1e-6)
    segments = [x.reshape(-1, 10).sum(1) for x in (learned, true)]
    assert metrics["reward_segment_corr"] == pytest.approx(np.corrcoef(*segments)[0, 1], abs=1e-6)
    assert 0.0 <= metrics["reward_pairs_ordered"] <= 1.0


def test_pretraining_updates_use_the_intrinsic_reward(tmp_path):
    learner, env = make(tmp_path, tiny_config())
    drive(learner, env, 100)
    assert learner.agent.updates == 100 - 60 + 1 and learner.entropy_stats.count > 1  # updates ran, on r_int


def test_fewer_sac_updates_than_steps_come_evenly_and_add_up(tmp_path):
    for per_step in (0.25, 1 / 3, 0.5, 1.0, 2.0):
        due = [updates_due(k, per_step) for k in range(300)]
        assert sum(due[:120]) == int(per_step * 120) and max(due) - min(due) <= 1
    learner, env = make(tmp_path, tiny_config(updates_per_step=0.5))
    drive(learner, env, 100)
    assert learner.agent.updates == (100 - 60 + 1) // 2  # every other step from the seed steps' end


@pytest.mark.slow
def test_a_resumed_learner_reuses_stored_labels_and_asks_nothing_twice(tmp_path):
    cfg = tiny_config()
    learner, env = make(tmp_path, cfg)
    drive(learner, env, 300)
    state = learner.state_dict()  # a checkpoint at step 300: one round done
    drive(learner, env, 700)  # a second and a third round are stored ...
    meta = learner.checkpoint_meta()
    learner.store.close()  # ... then the process dies

    resumed, env2 = make(tmp_path, cfg, name="moved")  # its directory renamed since: the checkpoint names the source
    resumed.load_state_dict(state)
    resumed.restore_meta(meta)
    assert resumed.step == 300 and resumed.asked == 30 and resumed.source == "run"
    trained_on, train_round = [], resumed.ensemble.train_round
    resumed.ensemble.train_round = lambda *a: trained_on.append(len(a[4])) or train_round(*a)
    drive(resumed, env2, 700)
    assert resumed.asked == 70 and resumed.store.count("run") == 70  # the stored rounds were reused
    assert [r["round"] for r in resumed.store.rounds("run")] == [0, 1, 2]
    assert trained_on == [60, 70]  # r̂ of round 1 learnt rounds 0 and 1, not round 2's labels ahead of time


def test_an_oracle_learner_stores_the_true_reward_and_asks_nothing(tmp_path):
    learner, env = make(tmp_path, tiny_config(oracle=True))
    drive(learner, env, 400)
    n = len(learner.buffer)
    assert learner.asked == 0 and learner.store.count("run") == 0 and learner.reward_ready
    np.testing.assert_allclose(learner.buffer.reward[:n], learner.buffer.next_obs[:n, 0] - learner.buffer.obs[:n, 0],
                               atol=1e-6)  # Drift's target reward: x-progress


def test_an_oracle_learner_resets_its_critic_when_pretraining_ends(tmp_path):
    learner, env = make(tmp_path, tiny_config(oracle=True, reset_updates=10))
    drive(learner, env, 239)  # pre-training ends at step 240 (60 seed + 180 unsupervised)
    critic, updates = learner.agent.critic, learner.agent.updates
    drive(learner, env, 240)
    assert learner.agent.critic is not critic  # the values of the intrinsic reward are forgotten
    assert learner.agent.updates == updates + 1 + 10  # this step's update and the reset's
    drive(learner, env, 300)
    assert learner.agent.critic is not critic and learner.asked == 0


class PrefersRightward:
    """A labeller that is not the scripted teacher: it judges by where each segment ends, not by a reward."""

    def __init__(self):
        self.rounds = []

    def label(self, pairs, rng, query):
        from rat.preferences.labeller import Labels

        self.rounds.append(query.round)
        y = (pairs.obs1[:, -1, 0] > pairs.obs0[:, -1, 0]).astype(np.float64)
        return Labels(np.arange(len(y)), y)

    def describe(self):
        return {"type": "rightward-test"}


def test_any_labeller_answers_the_queries_and_is_recorded_with_its_labels(tmp_path):
    from rat.preferences.labeller import Labeller

    labeller = PrefersRightward()
    assert isinstance(labeller, Labeller)
    learner = PebbleLearner(2, 2, tiny_config(budget=30), LabelStore(tmp_path / "labels.sqlite"), "run",
                            np.random.default_rng(0), labeller=labeller)
    drive(learner, Drift(np.random.default_rng(1)), 241)
    stored = learner.store.read("run")
    assert labeller.rounds == [0] and len(stored.rows) == 30
    assert all(row["labeller"] == {"type": "rightward-test"} for row in stored.rows)

