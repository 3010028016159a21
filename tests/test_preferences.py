"""Teacher, query strategies, Bradley-Terry, reward ensemble, state entropy, schedule."""

from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy import stats

from rat.agents.exploration import RunningMeanStd, knn_distance, state_entropy_reward
from rat.errors import RatError
from rat.preferences.labeller import Labeller, QueryRound
from rat.preferences.queries import kcenter_greedy, select_queries
from rat.preferences.reward_model import RewardEnsemble, RewardModelConfig, bradley_terry_loss, reward_agreement
from rat.preferences.schedule import FeedbackSchedule
from rat.preferences.segments import EpisodeHistory, SegmentPairs
from rat.preferences.teacher import ScriptedTeacher, TeacherConfig, segment_returns


def pairs_with_returns(r0, r1, length=4, obs_dim=3):
    """Pairs whose true per-step rewards are constant r/length, so segment returns are r0 and r1."""
    n = len(r0)
    rew0 = np.repeat(np.asarray(r0, float)[:, None] / length, length, 1)
    rew1 = np.repeat(np.asarray(r1, float)[:, None] / length, length, 1)
    z = np.zeros((n, length, obs_dim), np.float32)
    a = np.zeros((n, length, 1), np.float32)
    return SegmentPairs(z, a, rew0, z.copy(), a.copy(), rew1)


# --- the scripted teacher -----------------------------------------------------------------------------


def test_teacher_prefers_the_larger_return_and_label_one_means_the_second_segment():
    labels = ScriptedTeacher().label(pairs_with_returns([1.0, 5.0, 2.0], [3.0, 4.0, 2.5]), np.random.default_rng(0))
    assert labels.index.tolist() == [0, 1, 2]
    assert labels.y.tolist() == [1.0, 0.0, 1.0]


def test_teacher_mistake_rate_matches_by_a_binomial_test():
    rng = np.random.default_rng(1)
    n = 2000
    r0, r1 = rng.normal(size=n), rng.normal(size=n) + 10.0  # the second segment always better
    labels = ScriptedTeacher(TeacherConfig(mistake=0.1)).label(pairs_with_returns(r0, r1), rng)
    flipped = int((labels.y == 0.0).sum())
    assert stats.binomtest(flipped, n, 0.1).pvalue > 0.001, flipped
    assert 0.07 < flipped / n < 0.13


def test_boltzmann_teacher_follows_the_sigmoid_of_the_return_gap():
    rng = np.random.default_rng(2)
    n = 4000
    labels = ScriptedTeacher(TeacherConfig(beta=1.0)).label(pairs_with_returns(np.zeros(n), np.ones(n)), rng)
    expected = 1 / (1 + np.exp(-1.0))
    assert stats.binomtest(int(labels.y.sum()), n, expected).pvalue > 0.001


def test_exact_ties_are_labelled_equal_when_asked_and_first_preferred_as_b_pref_does():
    pairs = pairs_with_returns([0.0, 1.0, 2.0, 0.0], [0.0, 3.0, 2.0, 0.5])
    assert ScriptedTeacher(TeacherConfig(ties=True)).label(pairs, np.random.default_rng(0)).y.tolist() == [0.5, 1.0, 0.5, 1.0]
    b_pref = ScriptedTeacher().label(pairs, np.random.default_rng(0))
    assert b_pref.y.tolist() == [0.0, 1.0, 0.0, 1.0]


def test_skip_and_equal_thresholds():
    teacher = ScriptedTeacher(TeacherConfig(skip=0.5, equal=0.1))
    query = QueryRound(round=0, step=0, source="test", segment_return_scale=10.0)  # skip if both < 5; equal if |gap| < 1
    labels = teacher.label(pairs_with_returns([1.0, 6.0, 8.0, 2.0], [2.0, 6.5, 3.0, 9.0]), np.random.default_rng(0), query)
    assert isinstance(teacher, Labeller) and teacher.describe()["scale"] == 10.0
    assert labels.index.tolist() == [1, 2, 3]  # pair 0 skipped: both below 5
    assert labels.y.tolist() == [0.5, 0.0, 1.0]


def test_myopic_discount_weighs_recent_steps_more():
    reward = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(segment_returns(reward, 0.5), [0.25, 1.0])
    early = np.array([[2.0, 0.0, 0.0, 0.0]])
    late = np.array([[0.0, 0.0, 0.0, 1.0]])
    pairs = SegmentPairs(np.zeros((1, 4, 1)), np.zeros((1, 4, 1)), early, np.zeros((1, 4, 1)), np.zeros((1, 4, 1)), late)
    assert ScriptedTeacher().label(pairs, np.random.default_rng(0)).y.tolist() == [0.0]
    assert ScriptedTeacher(TeacherConfig(gamma=0.5)).label(pairs, np.random.default_rng(0)).y.tolist() == [1.0]


def test_bad_teacher_settings():
    with pytest.raises(RatError, match="mistake rate"):
        TeacherConfig(mistake=1.5)


# --- query strategies -------------------------------------------------------------------------------------


class StubEnsemble:
    """Members' P[second preferred] for 6 pairs, chosen so the rankings are known."""

    probs = np.array([
        [0.5, 0.1, 0.9, 0.5, 0.99, 0.6],
        [0.5, 0.9, 0.1, 0.5, 0.98, 0.4],
        [0.5, 0.5, 0.5, 0.5, 0.97, 0.5],
    ])

    def preference_probabilities(self, *args):
        return self.probs


def test_disagreement_and_entropy_pick_the_known_top_pairs():
    candidates = pairs_with_returns(np.zeros(6), np.zeros(6))
    rng = np.random.default_rng(0)
    # std over members: pairs 1 and 2 disagree most, then 5
    assert select_queries("disagreement", candidates, 3, StubEnsemble(), rng).tolist() == [1, 2, 5]
    # mean member entropy: pairs 0 and 3 (all 0.5) are most uncertain, then 5, then 1/2; 4 least
    picked = select_queries("entropy", candidates, 3, StubEnsemble(), rng).tolist()
    assert picked == [0, 3, 5]


def test_uniform_and_kcenter_strategies():
    rng = np.random.default_rng(0)
    candidates = pairs_with_returns(np.zeros(50), np.zeros(50))
    picked = select_queries("uniform", candidates, 10, StubEnsemble(), rng)
    assert len(set(picked.tolist())) == 10
    points = np.array([[0.0], [0.1], [10.0], [10.1], [5.0]], np.float32)
    assert sorted(kcenter_greedy(points, 3).tolist()) == [0, 2, 4] or sorted(kcenter_greedy(points, 3).tolist()) == [0, 3, 4]
    # already-labelled centres are avoided
    assert kcenter_greedy(points, 1, centres=np.array([[0.0], [10.0]], np.float32)).tolist() == [4]
    with pytest.raises(RatError, match="unknown query strategy"):
        select_queries("best", candidates, 1, StubEnsemble(), rng)


# --- Bradley-Terry and the reward ensemble ---------------------------------------------------------------------


def test_bradley_terry_loss_equals_a_hand_computation():
    r0, r1, y = torch.tensor([1.0, 0.0, 2.0]), torch.tensor([3.0, 0.0, 0.0]), torch.tensor([1.0, 0.5, 0.0])
    p_second = [np.exp(3) / (np.exp(1) + np.exp(3)), 0.5, np.exp(0) / (np.exp(2) + np.exp(0))]
    hand = -np.mean([np.log(p_second[0]), 0.5 * np.log(0.5) + 0.5 * np.log(0.5), np.log(1 - p_second[2])])
    assert bradley_terry_loss(r0, r1, y).item() == pytest.approx(hand, rel=1e-6)


def synthetic_pairs(n, rng, length=10):
    w = np.array([1.0, -2.0, 0.5, 0.0])
    obs0, obs1 = rng.normal(size=(n, length, 4)).astype(np.float32), rng.normal(size=(n, length, 4)).astype(np.float32)
    act = np.zeros((n, length, 1), np.float32)
    return SegmentPairs(obs0, act, obs0 @ w / 10, obs1, act.copy(), obs1 @ w / 10)


def test_reward_ensemble_learns_to_rank_held_out_pairs():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    train, held_out = synthetic_pairs(300, rng), synthetic_pairs(500, rng)
    y = ScriptedTeacher().label(train, rng).y
    ensemble = RewardEnsemble(4, 1, RewardModelConfig(hidden=32, layers=2, lr=1e-3, max_epochs=40, batch_size=64))
    before = [p.clone() for p in ensemble.parameters()]
    metrics = ensemble.train_round(train.obs0, train.act0, train.obs1, train.act1, y, rng)
    assert ensemble.epochs_run > 0 and any(not torch.equal(a, b) for a, b in zip(before, ensemble.parameters()))
    learned = ensemble.r_hat(held_out.obs1, held_out.act1).sum(1) - ensemble.r_hat(held_out.obs0, held_out.act0).sum(1)
    truth = held_out.reward1.sum(1) - held_out.reward0.sum(1)
    correct = int((np.sign(learned) == np.sign(truth)).sum())
    p = stats.binomtest(correct, 500, 0.5, alternative="greater").pvalue
    assert correct / 500 > 0.85 and p < 1e-10, f"held-out accuracy {correct / 500:.3f}, p={p:.2g}, {metrics}"


def test_a_round_can_be_capped_in_gradient_steps_whatever_the_labels_held():
    rng = np.random.default_rng(0)
    pairs = synthetic_pairs(1000, rng)
    y = ScriptedTeacher().label(pairs, rng).y
    config = RewardModelConfig(hidden=8, layers=1, max_epochs=50, batch_size=64, stop_accuracy=1.1)
    capped = RewardEnsemble(4, 1, replace(config, max_updates=20))
    metrics = capped.train_round(pairs.obs0, pairs.act0, pairs.obs1, pairs.act1, y, rng)
    assert metrics["reward_updates"] == 20 and metrics["reward_epochs"] == 2  # 16 batches, then 4 of the next epoch
    steps = [o.state_dict()["state"][0]["step"].item() for o in capped.optimizers]
    assert steps == [20.0] * config.members  # every member took exactly 20 Adam steps
    uncapped = RewardEnsemble(4, 1, replace(config, max_epochs=2))
    assert uncapped.train_round(pairs.obs0, pairs.act0, pairs.obs1, pairs.act1, y, rng)["reward_updates"] == 32


def test_a_held_out_round_learns_as_well_and_stops_itself_keeping_each_members_best_weights():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    train, test = synthetic_pairs(600, rng), synthetic_pairs(500, rng)
    y = ScriptedTeacher().label(train, rng).y
    config = RewardModelConfig(hidden=32, layers=2, lr=1e-3, batch_size=64, max_updates=2000, holdout=0.1,
                               check_every=10, patience=2, precision="bf16")
    ensemble = RewardEnsemble(4, 1, config)
    held = ensemble.held_out(600)
    assert held.sum() == 60 and np.array_equal(held[:300], ensemble.held_out(300))  # a label keeps its side
    metrics = ensemble.train_round(train.obs0, train.act0, train.obs1, train.act1, y, rng)
    assert 0 < metrics["reward_updates"] < 2000  # stopped by the held-out pairs, not the cap
    # each member's held-out loss at its kept weights is the round's best, i.e. no worse than where it stopped
    data = [torch.as_tensor(np.asarray(a, np.float32)) for a in (train.obs0, train.act0, train.obs1, train.act1, y)]
    idx = torch.as_tensor(np.flatnonzero(held))
    losses = [ensemble._held_out_loss(net, data, idx)[0] for net in ensemble.nets]
    assert np.isclose(np.mean(losses), metrics["reward_loss"], rtol=1e-4)
    learned = ensemble.r_hat(test.obs1, test.act1).sum(1) - ensemble.r_hat(test.obs0, test.act0).sum(1)
    correct = int((np.sign(learned) == np.sign(test.reward1.sum(1) - test.reward0.sum(1))).sum())
    p = stats.binomtest(correct, 500, 0.5, alternative="greater").pvalue
    assert correct / 500 > 0.85 and p < 1e-10, f"test accuracy {correct / 500:.3f}, p={p:.2g}, {metrics}"
    # the next round trains on the 100 new labels (90 of them) and 90 old ones, and knows which are new
    more = synthetic_pairs(100, rng)
    y_more = np.concatenate([y, ScriptedTeacher().label(more, rng).y])
    def cat(a, b):
        return np.concatenate([a, b])
    again = ensemble.train_round(cat(train.obs0, more.obs0), cat(train.act0, more.act0), cat(train.obs1, more.obs1),
                                 cat(train.act1, more.act1), y_more, rng)
    assert again["reward_new_labels"] == 100 and ensemble.labels_trained == 700
    state = ensemble.optimizer_state()
    fresh = RewardEnsemble(4, 1, config)
    fresh.load_optimizer_state(state)
    assert fresh.labels_trained == 700 and all(o.param_groups[0]["fused"] for o in fresh.optimizers)


def test_bad_reward_model_settings_are_refused():
    with pytest.raises(RatError, match="precision 'fp16'"):
        RewardModelConfig(precision="fp16")
    with pytest.raises(RatError, match="holdout must lie in"):
        RewardModelConfig(holdout=0.6)


def test_standardised_inputs_make_r_hat_blind_to_each_features_units_and_survive_a_checkpoint():
    rng = np.random.default_rng(0)
    pairs = synthetic_pairs(300, rng)
    y = ScriptedTeacher().label(pairs, rng).y
    scale, shift = np.array([0.1, 1.0, 50.0, 1.0], np.float32), np.array([0.0, 100.0, 0.0, -3.0], np.float32)

    def trained(normalize: bool, units: bool) -> RewardEnsemble:
        torch.manual_seed(0)
        ens = RewardEnsemble(4, 1, RewardModelConfig(hidden=16, layers=2, max_epochs=3, batch_size=64,
                                                     normalize_inputs=normalize))
        o0, o1 = (o * scale + shift if units else o for o in (pairs.obs0, pairs.obs1))
        ens.train_round(o0, pairs.act0, o1, pairs.act1, y, np.random.default_rng(1))
        return ens

    probe = rng.normal(size=(50, 4)).astype(np.float32)
    act = np.zeros((50, 1), np.float32)
    plain, rescaled = trained(True, False), trained(True, True)
    np.testing.assert_allclose(plain.r_hat(probe, act), rescaled.r_hat(probe * scale + shift, act), atol=2e-4)
    flat = np.concatenate([pairs.obs0 * scale + shift, pairs.obs1 * scale + shift]).reshape(-1, 4)
    np.testing.assert_allclose(rescaled.input_mean[:4].numpy(), flat.mean(0), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(rescaled.input_std[:4].numpy(), np.maximum(flat.std(0), RewardEnsemble.MIN_STD),
                               rtol=1e-3)
    assert rescaled.input_std[4] == RewardEnsemble.MIN_STD  # the action, constant here: floored, not divided by 0
    raw = trained(False, False), trained(False, True)  # raw inputs: the units change what is learnt
    assert np.abs(raw[0].r_hat(probe, act) - raw[1].r_hat(probe * scale + shift, act)).max() > 0.05
    assert "input_mean" not in raw[0].state_dict()  # older checkpoints, without it, still load into a raw ensemble
    restored = RewardEnsemble(4, 1, rescaled.config)
    restored.load_state_dict(rescaled.state_dict())
    np.testing.assert_array_equal(restored.r_hat(probe, act), rescaled.r_hat(probe, act))


def test_reward_is_tanh_bounded_and_the_mean_of_members():
    ens = RewardEnsemble(3, 2, RewardModelConfig(hidden=8, layers=1))
    obs, act = np.random.default_rng(0).normal(size=(7, 3)) * 100, np.ones((7, 2))
    members = ens.member_rewards(torch.as_tensor(obs, dtype=torch.float32), torch.as_tensor(act, dtype=torch.float32))
    assert members.shape == (3, 7) and members.abs().max() <= 1.0
    np.testing.assert_allclose(ens.r_hat(obs, act), members.mean(0).detach().numpy(), rtol=1e-6)


def test_r_hat_in_chunks_equals_one_batch_and_takes_a_single_transition():
    ens = RewardEnsemble(3, 2, RewardModelConfig(hidden=8, layers=1))
    obs, act = np.random.default_rng(0).normal(size=(7, 3)), np.ones((7, 2))
    np.testing.assert_allclose(ens.r_hat(obs, act, chunk=3), ens.r_hat(obs, act), rtol=1e-6)
    assert ens.r_hat(obs[0], act[0]).shape == () and np.isclose(ens.r_hat(obs[0], act[0]), ens.r_hat(obs, act)[0])


def test_reward_agreement_scores_a_learned_reward_against_the_true_one():
    true = np.random.default_rng(0).normal(size=1000)
    for learned, expected in ((true, 1.0), (2 * true + 3, 1.0), (-true, -1.0)):
        scores = reward_agreement(learned, true, segment=10)
        assert scores["step_corr"] == pytest.approx(expected) and scores["segment_corr"] == pytest.approx(expected)
        assert scores["pairs_ordered"] == (1.0 if expected > 0 else 0.0)
    # segments [1, 0, 2] against learned [0, 1, 3]: of the three distinct pairs, two are ordered right
    scores = reward_agreement([0, 0, 1, 0, 3, 0], [1, 0, 0, 0, 2, 0], segment=2)
    assert scores["pairs_ordered"] == pytest.approx(2 / 3, abs=0.02)
    assert reward_agreement(true, np.ones(1000), segment=10) == {}  # a constant true reward: nothing is defined


# --- state entropy --------------------------------------------------------------------------------------


def test_knn_state_entropy_equals_brute_force():
    rng = np.random.default_rng(0)
    pool = rng.normal(size=(300, 5)).astype(np.float32)
    obs = pool[rng.choice(300, 20, replace=False)]
    got = knn_distance(torch.as_tensor(obs), torch.as_tensor(pool), k=5, chunk=64).numpy()
    brute = np.array([np.sort(np.linalg.norm(pool - o, axis=1))[5] for o in obs])  # 0th is the point itself
    np.testing.assert_allclose(got, brute, rtol=1e-5)
    stats_ = RunningMeanStd()
    r = state_entropy_reward(torch.as_tensor(obs), torch.as_tensor(pool), stats_, k=5).numpy()
    np.testing.assert_allclose(r, got / stats_.std, rtol=1e-5)


def test_running_std_matches_numpy():
    rng = np.random.default_rng(0)
    s, xs = RunningMeanStd(epsilon=0.0), [rng.normal(3, 2, size=k) for k in (5, 50, 500)]
    for x in xs:
        s.update(x)
    allx = np.concatenate(xs)
    assert s.mean == pytest.approx(allx.mean()) and s.std == pytest.approx(allx.std())


# --- segments and schedule ------------------------------------------------------------------------------------


def test_segments_come_from_recent_episodes_in_order():
    history = EpisodeHistory(max_episodes=2)
    for ep in range(3):
        for t in range(60):
            history.add(np.full(2, 100 * ep + t), np.zeros(1), float(t), t == 59)
    pairs = history.sample_pairs(50, 10, np.random.default_rng(0))
    assert pairs.obs0.shape == (50, 10, 2)
    assert pairs.obs0[:, 0, 0].min() >= 100  # episode 0 was dropped
    np.testing.assert_array_equal(np.diff(pairs.obs0[..., 0], axis=1), 1.0)  # consecutive steps
    np.testing.assert_array_equal(pairs.reward0, pairs.obs0[..., 0] % 100)  # true rewards travel along


@pytest.mark.parametrize("budget", [0, 1, 127, 128, 1000, 3000])
def test_budget_accounting_is_exact(budget):
    schedule = FeedbackSchedule(budget=budget, first_step=100, every=50, per_round=128)
    rounds = schedule.rounds()
    assert sum(n for _, n in rounds) == budget
    assert all(n == 128 for _, n in rounds[:-1]) and all(0 < n <= 128 for _, n in rounds)
    assert [s for s, _ in rounds] == [100 + 50 * i for i in range(len(rounds))]
    assert schedule.queries_at(101, 0) == 0


def test_negative_budget_is_refused():
    with pytest.raises(RatError, match="budget must not be negative"):
        FeedbackSchedule(budget=-1)
