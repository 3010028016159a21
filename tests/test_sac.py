import numpy as np
import pytest
import torch
from scipy import stats

from rat.agents.buffer import ReplayBuffer
from rat.agents.networks import TanhGaussianActor, TwinCritic
from rat.agents.sac import SAC, SACConfig, critic_loss


class TrackTheSignal:
    """A one-step task shipped with the tests: observe x in [-0.8, 0.8]^2, be paid -(a - x0)^2."""

    def __init__(self, rng):
        self.rng = rng

    def reset(self):
        self.x = self.rng.uniform(-0.8, 0.8, 2).astype(np.float32)
        return self.x

    def step(self, action):
        return -float((action[0] - self.x[0]) ** 2)


def run_episodes(policy, env, n):
    return np.array([env.step(policy(env.reset())) for _ in range(n)])


@pytest.mark.slow
def test_sac_learns_a_tiny_task_within_a_bounded_number_of_updates():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    env = TrackTheSignal(rng)
    agent = SAC(2, 1, SACConfig(hidden=64, layers=2, lr=3e-3, alpha_lr=3e-3, batch_size=128, init_temperature=0.05))
    buffer = ReplayBuffer(2, 1, 5000)
    before = dict((k, v.clone()) for k, v in agent.actor.state_dict().items())
    for step in range(1500):
        obs = env.reset()
        action = agent.act(obs) if step >= 200 else rng.uniform(-1, 1, 1)
        buffer.add(obs, action, env.step(action), obs, terminated=True)
        if step >= 200:
            agent.update(buffer.sample(128, rng))
    assert agent.updates == 1300  # the update path ran, every time
    assert any(not torch.equal(before[k], v) for k, v in agent.actor.state_dict().items())
    trained = run_episodes(lambda o: agent.act(o, deterministic=True), env, 300)
    random = run_episodes(lambda o: rng.uniform(-1, 1, 1), env, 300)
    p = stats.mannwhitneyu(trained, random, alternative="greater").pvalue
    assert trained.mean() > -0.02 and p < 1e-6, f"trained {trained.mean():.4f} random {random.mean():.4f} p={p:.2g}"


def test_actor_log_prob_matches_a_change_of_variables_by_sampling():
    torch.manual_seed(0)
    actor = TanhGaussianActor(3, 2, hidden=16, layers=1)
    obs = torch.randn(1, 3).expand(4000, 3)
    action, log_prob = actor.sample(obs)
    mu, log_std = actor.distribution_params(obs[:1])
    base = torch.distributions.Normal(mu, log_std.exp())
    pre = torch.atanh(action.clamp(-0.999999, 0.999999))
    expected = (base.log_prob(pre) - torch.log1p(-action.pow(2) + 1e-12)).sum(-1)
    torch.testing.assert_close(log_prob, expected, atol=2e-3, rtol=1e-3)


def test_critic_target_bootstraps_through_truncation_but_not_termination():
    torch.manual_seed(0)
    actor, critic = TanhGaussianActor(2, 1, 8, 1), TwinCritic(2, 1, 8, 1)

    def target(terminated: float) -> float:
        batch = {"obs": torch.zeros(1, 2), "action": torch.zeros(1, 1), "reward": torch.ones(1),
                 "next_obs": torch.ones(1, 2), "terminated": torch.tensor([terminated])}
        torch.manual_seed(1)
        return critic_loss(critic, critic, actor, torch.tensor(0.0), batch, gamma=0.9)["target_q_mean"].item()

    torch.manual_seed(1)
    next_action, _ = actor.sample(torch.ones(1, 2))
    q_next = torch.min(*critic(torch.ones(1, 2), next_action)).item()
    assert target(0.0) == pytest.approx(1.0 + 0.9 * q_next, abs=1e-6)  # truncated: bootstraps
    assert target(1.0) == pytest.approx(1.0, abs=1e-6)  # terminated: reward only


def test_buffer_keeps_truncated_transitions_bootstrappable():
    buf = ReplayBuffer(1, 1, 10)
    buf.add([0.0], [0.0], 1.0, [1.0], terminated=False)  # a time-limit cut: truncated, not terminated
    buf.add([1.0], [0.0], 1.0, [2.0], terminated=True)
    assert buf.terminated[:2].tolist() == [0.0, 1.0]


def test_relabel_rewrites_every_stored_reward():
    buf = ReplayBuffer(2, 1, 100)
    rng = np.random.default_rng(0)
    for _ in range(150):  # wraps around the ring
        buf.add(rng.normal(size=2), rng.normal(size=1), 123.0, rng.normal(size=2), False)
    buf.relabel(lambda o, a, n: o[:, 0] + 10 * a[:, 0] - n[:, 1], chunk=7)
    expected = buf.obs[:, 0] + 10 * buf.action[:, 0] - buf.next_obs[:, 1]
    np.testing.assert_allclose(buf.reward, expected, rtol=1e-6)
    assert len(buf) == 100 and not np.any(buf.reward == 123.0)


def test_sampling_is_reproducible_from_the_generator():
    buf = ReplayBuffer(1, 1, 50)
    for i in range(50):
        buf.add([i], [0], i, [i], False)
    a = buf.sample(8, np.random.default_rng(3))["reward"]
    b = buf.sample(8, np.random.default_rng(3))["reward"]
    torch.testing.assert_close(a, b)


def test_buffer_state_round_trip():
    buf = ReplayBuffer(2, 1, 20)
    for i in range(25):
        buf.add([i, i], [i], i, [i + 1, i + 1], i % 3 == 0)
    copy = ReplayBuffer(2, 1, 20)
    copy.load_state_dict(buf.state_dict())
    assert (copy.size, copy.cursor) == (buf.size, buf.cursor)
    np.testing.assert_array_equal(copy.reward, buf.reward)


def test_a_bf16_update_keeps_float32_weights_and_heads_and_moves_every_network():
    torch.manual_seed(0)
    agent = SAC(6, 2, SACConfig(hidden=32, layers=2, batch_size=64, precision="bf16"))
    batch = {"obs": torch.randn(64, 6), "action": torch.rand(64, 2) * 2 - 1, "reward": torch.randn(64),
             "next_obs": torch.randn(64, 6), "terminated": torch.zeros(64)}
    before = {k: v.clone() for k, v in agent.state_dict().items()}
    with torch.autocast("cpu", dtype=torch.bfloat16):
        q1, _ = agent.critic(batch["obs"], batch["action"])
    assert q1.dtype == torch.float32  # the output layer runs in float32 even under autocast
    assert torch.allclose(q1, agent.critic(batch["obs"], batch["action"])[0], atol=0.05)  # bf16 hidden layers: close
    for _ in range(3):
        metrics = agent.update(batch)
    assert all(np.isfinite(v) for v in metrics.values())
    after = agent.state_dict()
    assert all(v.dtype == torch.float32 for v in after.values())
    for prefix in ("actor.", "critic.", "critic_target.", "log_alpha"):
        assert any(not torch.equal(before[k], after[k]) for k in after if k.startswith(prefix)), prefix
    assert agent.describe()["sac"]["precision"] == "bf16"


def test_fused_adam_resumes_fused_from_an_optimiser_state_written_without_it():
    torch.manual_seed(0)
    agent = SAC(6, 2, SACConfig(hidden=16, layers=1, batch_size=8))
    assert agent.critic_opt.param_groups[0]["fused"]
    batch = {"obs": torch.randn(8, 6), "action": torch.zeros(8, 2), "reward": torch.randn(8),
             "next_obs": torch.randn(8, 6), "terminated": torch.zeros(8)}
    plain = torch.optim.Adam(agent.critic.parameters(), lr=1e-4)  # as the agents before the fused kernel made it
    agent.critic_opt = plain
    agent.update(batch)
    state = agent.optimizer_state()
    assert state["critic"]["param_groups"][0]["fused"] is None
    resumed = SAC(6, 2, SACConfig(hidden=16, layers=1, batch_size=8))
    resumed.load_state_dict(agent.state_dict())
    resumed.load_optimizer_state(state)
    assert resumed.critic_opt.param_groups[0]["fused"] and resumed.updates == 1
    resumed.update(batch)
    assert all(s["step"].item() == 2 for s in resumed.critic_opt.state.values())


def test_an_unknown_precision_is_refused():
    from rat.errors import RatError

    with pytest.raises(RatError, match="precision 'half'"):
        SACConfig(precision="half")


def test_the_speed_benchmark_times_an_earlier_commits_agent_beside_this_one_without_mixing_them(tmp_path):
    import shutil
    import sys
    from pathlib import Path

    from benchmark_scripts import load

    import rat

    speed = load("speed")
    src = tmp_path / "src"
    shutil.copytree(Path(rat.__file__).parent, src / "rat")  # stands in for an earlier commit's src/
    modules = dict(sys.modules)
    base = speed.import_base(str(src))
    assert base["file"].startswith(str(src)) and base["SAC"] is not SAC
    assert sys.modules["rat.agents.sac"] is modules["rat.agents.sac"] and str(src) not in sys.path
    times = speed.interleaved({"base": speed.ours(base["SAC"], base["SACConfig"], 32),
                               "this": speed.ours(SAC, SACConfig, 32, precision="bf16")}, updates=2, repeats=2)
    assert set(times) == {"base", "this"} and all(t > 0 for t in times.values())
