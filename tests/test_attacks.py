"""Threat model, RAT's losses and hypergradient, gradient isolation, the combined behaviour policy."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from point_env import HORIZON, PointGoal
from scipy import stats

from rat.agents.networks import TanhGaussianActor, TwinCritic
from rat.agents.sac import SAC, SACConfig
from rat.attacks.losses import (
    Adversary,
    Imitation,
    WeightingNetwork,
    gaussian_kl,
    hypergradient,
    inner_loss,
    saturation,
)
from rat.attacks.rat import CombinedBehaviourPolicy, RATConfig, adversary_update, weighting_update
from rat.attacks.refine import refined_function
from rat.attacks.threat import NORMS, AttackedObservation, ThreatModel, perturbation_norm, project, random_delta
from rat.errors import RatError
from rat.victims import ModuleVictim

# --- threat model ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("norm", NORMS)
def test_perturbations_stay_in_the_ball_on_random_inputs_at_large_scale(norm):
    torch.manual_seed(0)
    obs = torch.randn(20_000, 39, dtype=torch.float64) * 5
    delta = torch.randn(20_000, 39, dtype=torch.float64) * torch.logspace(-3, 3, 20_000, dtype=torch.float64)[:, None]
    for eps in (0.0, 1e-3, 0.1, 2.5):
        threat = ThreatModel(eps, norm)
        attacked = threat.perturb(obs, delta)
        assert perturbation_norm((attacked - obs).numpy(), norm).max() <= eps * (1 + 1e-9) + 1e-12
        assert threat.contains(obs.numpy(), attacked.numpy(), tolerance=1e-9)
    np.testing.assert_array_equal(ThreatModel(0.0, norm).perturb(obs, delta).numpy(), obs.numpy())  # epsilon 0 changes nothing
    assert not ThreatModel(0.1, norm).contains(obs.numpy(), obs.numpy() + 1.0)


@pytest.mark.parametrize("norm", ["linf", "l2", "l1"])
def test_projection_leaves_points_inside_the_ball_alone_and_is_the_nearest_point(norm):
    torch.manual_seed(1)
    small = torch.rand(100, 6, dtype=torch.float64) * 0.01
    torch.testing.assert_close(project(small, norm), small)
    big = torch.randn(200, 6, dtype=torch.float64) * 3
    p = project(big, norm)
    # nearest point: no random point of the ball is closer to the input than its projection
    cands = torch.stack([project(torch.randn(6, dtype=torch.float64) * 2, norm) for _ in range(500)])
    d_proj = (big - p).norm(dim=1)
    d_cand = torch.cdist(big, cands).min(1).values
    assert torch.all(d_proj <= d_cand + 1e-9)


def test_l1_projection_matches_a_bisection_on_the_threshold():
    torch.manual_seed(2)
    v = torch.randn(50, 9, dtype=torch.float64) * 4
    got = project(v, "l1")
    for row, out in zip(v, got):
        lo, hi = 0.0, float(row.abs().max())
        for _ in range(200):
            theta = (lo + hi) / 2
            lo, hi = (theta, hi) if (row.abs() - theta).clamp(min=0).sum() > 1 else (lo, theta)
        expected = torch.sign(row) * (row.abs() - theta).clamp(min=0)
        torch.testing.assert_close(out, expected, atol=1e-9, rtol=0)


@pytest.mark.parametrize("norm", NORMS)
def test_random_attack_is_in_the_unit_ball(norm):
    rng = np.random.default_rng(0)
    d = np.array([random_delta(rng, 39, norm) for _ in range(2000)])
    assert perturbation_norm(d, norm).max() <= 1 + 1e-12


def test_the_wrapper_shows_the_attacked_observation_and_keeps_the_true_state():
    env = AttackedObservation(PointGoal(0), lambda o: np.array([1.0, -1.0, 1.0, 1.0]) * 5, ThreatModel(0.1, "linf"))
    obs, info = env.reset(seed=3)
    np.testing.assert_allclose(obs - info["true_obs"], [0.1, -0.1, 0.1, 0.1])
    inner = env.unwrapped
    np.testing.assert_allclose(info["true_obs"], np.concatenate([inner.p, inner.g]))
    obs, _, _, _, info = env.step(np.zeros(2))
    assert info["perturbation_norm"] == pytest.approx(0.1) and max(env.norms) <= 0.1 + 1e-12
    with pytest.raises(RatError, match="epsilon must be"):
        ThreatModel(-0.1)
    with pytest.raises(RatError, match="unknown norm"):
        ThreatModel(0.1, "l3")


# --- KL, hypergradient ------------------------------------------------------------------------------------------


def test_gaussian_kl_matches_torch_distributions():
    torch.manual_seed(0)
    m1, m2, log_s2 = torch.randn(7, 4), torch.randn(7, 4), torch.randn(7, 4) * 0.5
    for s1 in (1.0, 0.3):
        ours = gaussian_kl(m1, s1, m2, log_s2)
        ref = torch.distributions.kl_divergence(torch.distributions.Normal(m1, torch.full_like(m1, s1)),
                                                torch.distributions.Normal(m2, log_s2.exp())).sum(-1)
        torch.testing.assert_close(ours, ref, rtol=1e-5, atol=1e-6)
    released = gaussian_kl(m1, 1.0, m2, log_s2, form="released")
    assert not torch.allclose(released, gaussian_kl(m1, 1.0, m2, log_s2))  # the released helper differs


class TinyVictim(torch.nn.Module):
    def __init__(self, obs_dim, act_dim):
        super().__init__()
        self.net = torch.nn.Sequential(torch.nn.Linear(obs_dim, 8), torch.nn.Tanh(), torch.nn.Linear(8, act_dim), torch.nn.Tanh())

    def act(self, obs):
        return self.net(obs)


def tiny_problem(dtype=torch.float64):
    torch.manual_seed(0)
    d, a = 3, 2
    parts = dict(adversary=Adversary(d, hidden=6, layers=1), weighting=WeightingNetwork(d, hidden=5),
                 victim=TinyVictim(d, a), intention=TanhGaussianActor(d, a, 6, 1), critic=TwinCritic(d, a, 6, 1))
    for m in parts.values():
        m.to(dtype)
    parts["victim"].requires_grad_(False)
    obs_i, obs_o = torch.randn(16, d, dtype=dtype), torch.randn(12, d, dtype=dtype)
    noise_i, noise_o = torch.randn(16, d, dtype=dtype), torch.randn(12, d, dtype=dtype)
    return parts, obs_i, noise_i, obs_o, noise_o


def test_hypergradient_matches_a_finite_difference():
    p, obs_i, noise_i, obs_o, noise_o = tiny_problem()
    temperature, eta, eps = torch.tensor(0.1, dtype=torch.float64), 0.5, 0.3
    objective = Imitation(p["victim"], p["intention"], p["critic"], temperature, ThreatModel(eps, "linf"))
    grads = hypergradient(objective, p["adversary"], p["weighting"], obs_i, noise_i, obs_o, noise_o, eta)

    def outer_after_virtual_step():
        params = {k: v.detach().requires_grad_(True) for k, v in p["adversary"].named_parameters()}
        kl = objective.kl(p["adversary"], params, obs_i, noise_i)
        with torch.no_grad():
            w = p["weighting"](obs_i)
        g = torch.autograd.grad(inner_loss(w, kl), list(params.values()))
        virtual = {k: v - eta * gi for (k, v), gi in zip(params.items(), g)}
        with torch.no_grad():
            return objective.outer(p["adversary"], virtual, obs_o, noise_o).item()

    checked = 0
    for param, grad in zip(p["weighting"].parameters(), grads):
        for idx in list(np.ndindex(param.shape))[:4]:
            old = param[idx].item()
            values = []
            for shifted in (old + 1e-6, old - 1e-6):
                with torch.no_grad():
                    param[idx] = shifted
                values.append(outer_after_virtual_step())
            with torch.no_grad():
                param[idx] = old
            up, down = values
            assert grad[idx].item() == pytest.approx((up - down) / 2e-6, rel=1e-4, abs=1e-10)
            checked += 1
    assert checked >= 12 and any(g.abs().sum() > 0 for g in grads)




def test_batch_mean_hypergradient_is_a_different_approximation():
    p, obs_i, noise_i, obs_o, noise_o = tiny_problem()
    objective = Imitation(p["victim"], p["intention"], p["critic"], torch.tensor(0.1, dtype=torch.float64),
                          ThreatModel(0.3, "linf"))
    args = (objective, p["adversary"], p["weighting"], obs_i, noise_i, obs_o, noise_o, 0.5)
    exact, approx = hypergradient(*args), hypergradient(*args, form="batch-mean")
    assert all(a.shape == b.shape for a, b in zip(exact, approx))
    assert not all(torch.allclose(a, b) for a, b in zip(exact, approx))


# --- gradient isolation ------------------------------------------------------------------------------------------


def snapshot(*modules):
    return [[q.detach().clone() for q in m.parameters()] for m in modules]


def changed(before, module):
    return any(not torch.equal(a, b) for a, b in zip(before, module.parameters()))


def isolation_setup(ablation="none"):
    torch.manual_seed(0)
    env = PointGoal()
    # a victim with weights, so "the victim never changes" is not vacuous
    mlp = torch.nn.Sequential(torch.nn.Linear(4, 16), torch.nn.Tanh(), torch.nn.Linear(16, 2), torch.nn.Tanh())
    victim = ModuleVictim(mlp, env.observation_space, env.action_space)
    intention = SAC(4, 2, SACConfig(hidden=16, layers=1, batch_size=8))
    adversary, weighting = Adversary(4, hidden=16), WeightingNetwork(4, hidden=8)
    cfg = RATConfig(epsilon=0.1, ablation=ablation, horizon=HORIZON)
    return victim, intention, adversary, weighting, cfg, torch.randn(32, 4)


@pytest.mark.parametrize("ablation", ["none", "no-intention"])
def test_inner_step_moves_only_the_adversary_and_never_the_victim(ablation):
    victim, intention, adversary, weighting, cfg, obs = isolation_setup(ablation)
    before = snapshot(adversary, weighting, intention.actor, intention.critic, victim)
    opt = torch.optim.Adam(adversary.parameters(), lr=1e-2)
    objective = Imitation(victim, intention.actor, intention.critic, intention.alpha, cfg.threat)
    adversary_update(adversary, opt, weighting, objective, obs, cfg.ablation)
    assert changed(before[0], adversary) and len(before[4]) == 4  # the victim has weights to protect
    for b, m in zip(before[1:], (weighting, intention.actor, intention.critic, victim)):
        assert not changed(b, m)
        assert all(q.grad is None for q in m.parameters())


def test_saturation_counts_the_components_of_delta_at_the_balls_edge():
    torch.manual_seed(0)
    adversary, obs = Adversary(4, hidden=16, layers=1), torch.randn(64, 4)
    assert saturation(adversary, obs) < 0.05  # a fresh adversary is near the centre
    with torch.no_grad():
        adversary.policy.trunk[-1].bias[:2] += 50.0  # the means of two of four components, far past tanh's range
    assert saturation(adversary, obs) == pytest.approx(0.5)


def test_refinement_narrows_each_states_imitation_gap_inside_the_ball_and_never_changes_the_victim():
    victim, intention, adversary, _, _, _ = isolation_setup()
    threat = ThreatModel(1.0)  # a ball wide enough to move this small victim's action
    before = snapshot(victim)
    obs = np.random.default_rng(0).normal(size=(40, 4))
    network, refined = [], []
    for o in obs:  # each state on its own (no warm start from another): the network's Δ, then 30 steps from it
        refined_function(adversary, intention.actor, victim, threat, 0, gaps=network)(o)
        delta = refined_function(adversary, intention.actor, victim, threat, 30, gaps=refined)(o)
        assert np.abs(delta).max() < 1.0  # through tanh: inside the ball
    network, refined = np.array(network), np.array(refined)
    assert (refined <= network + 1e-6).all()  # the best Δ seen, so never worse than where it starts
    assert refined.mean() < 0.7 * network.mean(), (refined.mean(), network.mean())
    assert stats.wilcoxon(network, refined, alternative="greater").pvalue < 1e-3
    with torch.no_grad():
        start = adversary(torch.as_tensor(obs[:1], dtype=torch.float32)).squeeze(0).numpy()
    np.testing.assert_allclose(refined_function(adversary, intention.actor, victim, threat, 0)(obs[0]), start,
                               atol=1e-3)  # no steps: the network's Δ
    assert not changed(before[0], victim) and all(p.grad is None for p in victim.parameters())


def test_refinement_refines_where_the_caller_turned_gradients_off():
    victim, intention, adversary, _, _, _ = isolation_setup()
    obs, threat = np.random.default_rng(2).normal(size=4), ThreatModel(1.0)
    free = refined_function(adversary, intention.actor, victim, threat, 10)(obs)
    with torch.no_grad():  # as r̂ scores an attack's episodes (policy_learned_return)
        inside = refined_function(adversary, intention.actor, victim, threat, 10)(obs)
        network = refined_function(adversary, intention.actor, victim, threat, 0)(obs)
    np.testing.assert_allclose(inside, free, atol=1e-6)
    assert np.abs(inside - network).max() > 1e-3  # it moved from the network's Δ


def test_refinement_starts_from_the_previous_observations_delta_when_that_fits_better():
    victim, intention, adversary, _, _, _ = isolation_setup()
    obs, gaps = np.random.default_rng(1).normal(size=4), []
    refine = refined_function(adversary, intention.actor, victim, ThreatModel(1.0), 5, gaps=gaps)
    for _ in range(4):  # the same state again: each call goes on from where the last one ended
        refine(obs)
    assert gaps[3] < gaps[0] and all(b <= a + 1e-6 for a, b in zip(gaps, gaps[1:])), gaps




class FirstDimensionCritic(torch.nn.Module):
    """A critic that values only the first action dimension, raising it: Q(s, a) = a₀ (both heads)."""

    def forward(self, obs, action):
        return action[:, 0], action[:, 0]


def test_refinement_by_the_critic_climbs_q_where_the_gap_loss_chases_pi_thetas_action():
    victim, intention, adversary, _, _, _ = isolation_setup()
    threat, obs = ThreatModel(0.5), np.random.default_rng(0).normal(size=(40, 4))
    critic, before = FirstDimensionCritic(), snapshot(victim, intention.critic)
    first = {}  # the attacked victim's first action dimension, by refinement loss
    for loss, steps in (("network", 0), ("l2", 30), ("q", 30)):
        values = []
        for o in obs:
            delta = refined_function(adversary, intention.actor, victim, threat, steps, loss="l2" if steps == 0 else loss,
                                     critic=critic)(o)
            assert np.abs(delta).max() < 1.0  # through tanh: inside the ball
            s = torch.as_tensor(o, dtype=torch.float32).unsqueeze(0)
            with torch.no_grad():
                values.append(victim.act(threat.perturb(s, torch.as_tensor(delta).float().unsqueeze(0)))[0, 0].item())
        first[loss] = np.array(values)
    assert (first["q"] >= first["network"] - 1e-6).all()  # the best Δ seen: never below where it starts
    assert first["q"].mean() > first["l2"].mean() + 0.1, (first["q"].mean(), first["l2"].mean())
    assert stats.wilcoxon(first["q"], first["l2"], alternative="greater").pvalue < 1e-3
    # π_θ's own twin critic: each state's min Q never falls below the network's Δ's, and nothing trains
    for o in obs[:5]:
        s = torch.as_tensor(o, dtype=torch.float32).unsqueeze(0)
        q = {}
        for steps in (0, 20):
            delta = refined_function(adversary, intention.actor, victim, threat, steps, loss="q",
                                     critic=intention.critic)(o)
            with torch.no_grad():
                q[steps] = torch.min(*intention.critic(
                    s, victim.act(threat.perturb(s, torch.as_tensor(delta).float().unsqueeze(0))))).item()
        assert q[20] >= q[0] - 1e-5
    assert not changed(before[0], victim) and not changed(before[1], intention.critic)
    assert all(p.grad is None for p in [*victim.parameters(), *intention.critic.parameters()])
    with pytest.raises(RatError, match="refine-loss 'q' climbs π_θ's critic, and none was given"):
        refined_function(adversary, intention.actor, victim, threat, 5, loss="q")


def test_refinement_by_l2_or_q_takes_the_critics_delta_exactly_where_l2_leaves_a_gap_above_the_threshold():
    victim, intention, adversary, _, _, _ = isolation_setup()
    threat, obs, critic = ThreatModel(0.5), np.random.default_rng(0).normal(size=(40, 4)), FirstDimensionCritic()

    def refine(loss, **kwargs):  # each state on its own: Δ, and the gap left
        deltas, gaps = [], []
        for o in obs:
            deltas.append(refined_function(adversary, intention.actor, victim, threat, 30, gaps=gaps, loss=loss,
                                           critic=critic, **kwargs)(o))
        return np.array(deltas), np.array(gaps)

    (by_l2, l2_gaps), (by_q, _) = refine("l2"), refine("q")
    threshold = float(np.median(l2_gaps))
    mixed, _ = refine("l2-or-q", switch_gap=threshold)
    far = l2_gaps > threshold
    assert 0 < far.sum() < len(obs) and np.abs(by_q - by_l2).max(axis=1).min() > 1e-3  # the two losses differ
    np.testing.assert_allclose(mixed[~far], by_l2[~far], atol=1e-6)
    np.testing.assert_allclose(mixed[far], by_q[far], atol=1e-6)
    np.testing.assert_allclose(refine("l2-or-q", switch_gap=float("inf"))[0], by_l2, atol=1e-6)
    with pytest.raises(RatError, match="refine-loss 'l2-or-q' climbs π_θ's critic, and none was given"):
        refined_function(adversary, intention.actor, victim, threat, 5, loss="l2-or-q")
    with pytest.raises(RatError, match="refine-switch-gap must be ≥ 0"):
        RATConfig(refine_switch_gap=-1.0)
    with pytest.raises(RatError, match="refine-switch-gap must be ≥ 0"):  # nor past the config, from a saved run
        refined_function(adversary, intention.actor, victim, threat, 5, loss="l2-or-q", critic=critic, switch_gap=-1.0)


def test_outer_step_moves_only_the_weighting_network():
    victim, intention, adversary, weighting, cfg, obs = isolation_setup()
    before = snapshot(adversary, weighting, intention.actor, intention.critic)
    opt = torch.optim.Adam(weighting.parameters(), lr=1e-2)
    objective = Imitation(victim, intention.actor, intention.critic, intention.alpha, cfg.threat)
    weighting_update(weighting, opt, adversary, objective, obs, torch.randn(32, 4), cfg.adversary_lr, cfg.hypergradient)
    assert changed(before[1], weighting)
    for b, m in zip([before[0], *before[2:]], (adversary, intention.actor, intention.critic)):
        assert not changed(b, m) and all(q.grad is None for q in m.parameters())


# --- the combined behaviour policy ---------------------------------------------------------------------------------


def test_combined_policy_switches_at_the_drawn_episode_step():
    policy = CombinedBehaviourPolicy(horizon=10)
    rng = np.random.default_rng(0)
    switches = []
    for _ in range(5000):
        policy.start_episode(rng)
        h = policy.switch
        switches.append(h)
        assert [policy.victim_acts(t) for t in range(10)] == [t < h for t in range(10)]
    counts = np.bincount(switches, minlength=10)
    assert len(counts) == 10 and stats.chisquare(counts).pvalue > 0.001  # h ~ U{0..H-1}




def test_ablation_modes_fix_the_switch():
    rng = np.random.default_rng(0)
    victim_only, intention_only = CombinedBehaviourPolicy(8, "victim"), CombinedBehaviourPolicy(8, "intention")
    victim_only.start_episode(rng)
    intention_only.start_episode(rng)
    assert all(victim_only.victim_acts(t) for t in range(8)) and not any(intention_only.victim_acts(t) for t in range(8))


def test_bad_attack_settings():
    with pytest.raises(RatError, match="epsilon must be"):
        RATConfig(epsilon=-1)
    with pytest.raises(RatError, match="unknown ablation"):
        RATConfig(ablation="no-everything")
    with pytest.raises(RatError, match="refine-loss must be one of l2, q, l2-or-q, got 'kl'"):
        RATConfig(refine_loss="kl")
    with pytest.raises(RatError, match="refine-steps must be"):
        RATConfig(refine_steps=-1)
    with pytest.raises(RatError, match="no-intention ablation"):
        RATConfig(refine_steps=10, ablation="no-intention")


class _GoalXReward:
    """A stand-in for r̂ on the point environment: the further right of the goal, the better."""

    def r_hat(self, obs, action):
        return float(obs[0] - obs[2])


def test_selection_by_the_learned_reward_keeps_the_snapshot_it_scores_best(tmp_path):
    from point_env import point_victim

    from rat.attacks.saved import learned_return, select_by_learned_reward
    from rat.checkpoint import save_checkpoint

    cfg = RATConfig(epsilon=0.1, eval_episodes=3)
    victim, reward = point_victim(), _GoalXReward()
    torch.manual_seed(0)
    snapshots = [Adversary(4, 16) for _ in range(3)]
    for i, snap in enumerate(snapshots):
        with torch.no_grad():  # constant perturbations: shift the observed goal left, not at all, right
            last = snap.policy.trunk[-1]
            last.weight.zero_()
            last.bias.zero_()
            last.bias[2] = 3.0 * (i - 1)  # the mean of Δ for the observed goal's x
        pi_theta, critic = TanhGaussianActor(4, 2, 8, 1), TwinCritic(4, 2, 8, 1)  # what each snapshot imitated
        with torch.no_grad():
            pi_theta.trunk[0].weight.fill_(float(i))
            critic.q1[0].bias.fill_(float(i))
        save_checkpoint(tmp_path / f"adversary-{1000 * (i + 1)}", "adversary-snapshot",
                        {"adversary": snap.state_dict(), "intention": pi_theta.state_dict(),
                         "critic": critic.state_dict()}, {"step": 1000 * (i + 1)})
    current = Adversary(4, 16)  # the adversary at the end of training: another candidate ("last")
    scores = [learned_return(victim, a, PointGoal(3), reward, cfg.threat, 3, seed=3 * 10**7) for a in snapshots + [current]]
    expected = [a.state_dict() for a in snapshots + [current]][int(np.argmax(scores))]
    expected = {k: v.clone() for k, v in expected.items()}
    result = select_by_learned_reward(tmp_path, current, victim, reward, PointGoal(3), cfg)
    best = int(np.argmax(scores))
    assert result["selected_step"] == (1000 * (best + 1) if best < 3 else cfg.total_steps)
    assert all(torch.equal(a, b) for a, b in zip(current.state_dict().values(), expected.values()))
    assert max(result["learned_returns"].values()) == pytest.approx(max(scores), abs=1e-3)
    assert len(set(round(x, 6) for x in scores)) == 4 and best == 2  # they differ; shifting the goal right wins
    # refine towards its own π_θ, with its own critic
    assert torch.equal(result["imitated"].actor.trunk[0].weight, torch.full((8, 4), 2.0))
    assert torch.equal(result["imitated"].critic.q1[0].bias, torch.full((8,), 2.0))
    with pytest.raises(RatError, match="oracle"):
        from rat.preferences.pebble import PebbleConfig
        RATConfig(select="reward", pebble=PebbleConfig(oracle=True))


class EndsEarly(gym.Wrapper):
    """The point task, each episode ending at its own step (25 to 34, by its seed): lockstep must not wait."""

    def reset(self, *, seed=None, options=None):
        self.length, self.t = 25 + (seed or 0) % 10, 0
        return self.env.reset(seed=seed, options=options)

    def step(self, action):
        self.t += 1
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated or self.t >= self.length, truncated, info


def alone_and_in_lockstep(victim, threat: ThreatModel, steps: int, radius: float, episodes: int):
    """A refined attack's evaluation one episode at a time and three at a time (each with the gaps it left), on the
    point task with episodes of their own lengths; success is coming within ``radius`` of the goal."""
    from rat.attacks.evaluation import evaluate_attack
    from rat.envs.targets import TargetBehaviour

    _, intention, adversary, _, _, _ = isolation_setup()
    near = TargetBehaviour("near", f"within {radius} of the goal", lambda *a: 0.0,
                           lambda info: float(np.linalg.norm(info["point"] - info["goal"])) < radius)
    runs = []
    for width in (1, 3):
        gaps: list[float] = []
        attack = refined_function(adversary, intention.actor, victim, threat, steps, gaps=gaps)
        runs.append((evaluate_attack(victim, attack, EndsEarly(PointGoal()), near, threat, episodes, 500,
                                     make_env=lambda: EndsEarly(PointGoal()), lockstep=width), gaps))
    return runs


def test_a_refined_attack_evaluated_in_lockstep_gives_each_episode_its_own_numbers():
    """Ten episodes three at a time, Δ refined for all the running ones at once, against one at a time."""
    from point_env import point_victim

    # a budget that keeps 3 of these 10 episodes near the goal
    (alone, gaps_alone), (together, gaps_together) = alone_and_in_lockstep(point_victim(), ThreatModel(0.025), 10,
                                                                           0.06, 10)
    assert 0 < sum(alone.result.successes) < 10  # the attack decides some episodes and not others
    assert together.result.successes == alone.result.successes
    assert together.result.first_success_step == alone.result.first_success_step
    np.testing.assert_allclose(together.result.mean_return, alone.result.mean_return, rtol=1e-5)
    assert [r[:2] for r in together.records] == [r[:2] for r in alone.records]  # every observation, once, in order
    assert together.steps == alone.steps == sum(26 + (500 + i) % 10 for i in range(10))  # the last one's too
    np.testing.assert_allclose([r[2] for r in together.records], [r[2] for r in alone.records], atol=1e-6)
    np.testing.assert_allclose(sorted(gaps_together), sorted(gaps_alone), atol=1e-4)
    assert together.within_budget


def test_a_refined_attack_on_a_sequence_victim_follows_each_episodes_context_alone_and_in_lockstep(tmp_path):
    """Refinement runs the victim on its context: the attack keeps each episode's as the victim's keeper does."""
    pytest.importorskip("transformers", reason="pip install 'rat[dt]' (the dev extra has it)")
    from point_env import point_dt_victim

    from rat.victims.base import VictimPolicy

    victim = point_dt_victim(tmp_path / "dt")
    _, intention, adversary, _, _, _ = isolation_setup()
    threat = ThreatModel(0.1)

    # one episode by hand: what the attack keeps is what the victim's keeper keeps
    attack = refined_function(adversary, intention.actor, victim, threat, 5)
    env, policy = AttackedObservation(EndsEarly(PointGoal()), attack, threat), VictimPolicy(victim)
    obs, _ = env.reset(seed=3)
    policy.reset()
    done = False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(policy(obs))
        policy.observe(reward)
        done = terminated or truncated
    assert policy.context.length == 3 and int(policy.context.timesteps[0, -1]) == 28
    torch.testing.assert_close(victim.pack_context(attack.contexts[0]), victim.pack_context(policy.context))
    with_history = attack.batch(obs[None], [0])
    attack.reset(0)
    assert not np.allclose(attack.batch(obs[None], [0]), with_history)  # the context reaches the refinement
    passes = []
    victim._past = lambda *inputs, past=victim._past: passes.append(1) or past(*inputs)
    attack.batch(obs[None], [0])
    assert len(passes) == 2  # the past ran once for the warm start's comparison and once for the five steps
    del victim._past

    (alone, gaps_alone), (together, gaps_together) = alone_and_in_lockstep(victim, threat, 5, 0.1, 6)
    assert together.result.successes == alone.result.successes
    np.testing.assert_allclose(together.result.mean_return, alone.result.mean_return, rtol=1e-5)
    assert [r[:2] for r in together.records] == [r[:2] for r in alone.records]
    np.testing.assert_allclose(sorted(gaps_together), sorted(gaps_alone), atol=1e-4)
    assert together.within_budget


def test_the_refine_choice_script_records_an_attacked_episode_as_the_teacher_sees_it():
    from benchmark_scripts import load
    from point_env import BESIDE, point_victim

    true_episode = load("refine_choice").true_episode
    still = AttackedObservation(PointGoal(), lambda obs: np.zeros(4), ThreatModel(0.1))
    # the goal seen to the right, the point to the left: the victim overshoots the goal, through the target beside it
    rightward = AttackedObservation(PointGoal(), lambda obs: np.array([-1.0, 0.0, 1.0, 0.0]), ThreatModel(0.1))
    (o0, a0, r0, ok0), (o1, a1, r1, ok1) = (true_episode(point_victim(), env, BESIDE, 5) for env in (still, rightward))
    assert o0.shape == (HORIZON, 4) and a1.shape == (HORIZON, 2) and r0.shape == ok0.shape == (HORIZON,)
    np.testing.assert_array_equal(o0[0], o1[0])  # the same start, the true observation
    assert not ok0.any() and ok1.any() and r1.sum() > r0.sum()
    np.testing.assert_allclose(o1[1, :2], o1[0, :2] + 0.05 * np.clip(a1[0], -1, 1))  # the true state moved by the action

