import json

import gymnasium as gym
import numpy as np
import pytest
import torch
from torch import nn

from rat.agents.networks import TanhGaussianActor
from rat.envs import make_task
from rat.errors import RatError
from rat.victims import (
    ModuleVictim,
    Victim,
    check_compatible,
    load_rat_victim,
    load_sb3_victim,
    load_victim,
    save_victim,
)

sb3 = pytest.importorskip("stable_baselines3")


@pytest.fixture(scope="module", params=["SAC", "TD3", "PPO"])
def sb3_model(request, tmp_path_factory):
    """A Stable-Baselines3 model trained for a few hundred steps here, saved as its own zip format."""
    algo = getattr(sb3, request.param)
    env = gym.make("Pendulum-v1")
    kwargs = {"n_steps": 128, "batch_size": 64} if request.param == "PPO" else {"learning_starts": 50}
    model = algo("MlpPolicy", env, seed=0, policy_kwargs={"net_arch": [32, 32]}, **kwargs)
    model.learn(300)
    path = tmp_path_factory.mktemp("sb3") / f"{request.param}.zip"
    model.save(path)
    return model, path


def test_sb3_adapter_reproduces_the_models_deterministic_actions(sb3_model):
    model, path = sb3_model
    victim = load_sb3_victim(path)
    assert isinstance(victim, Victim)
    obs = np.random.default_rng(0).uniform(-1, 1, (64, 3)).astype(np.float32)
    expected, _ = model.predict(obs, deterministic=True)
    got = victim.act(torch.as_tensor(obs)).numpy()
    np.testing.assert_allclose(got, expected, atol=1e-5)
    assert victim.observation_space.shape == (3,) and victim.action_space.shape == (1,)


def test_sb3_adapter_respects_a_custom_activation(tmp_path):
    env = gym.make("Pendulum-v1")
    model = sb3.SAC("MlpPolicy", env, seed=0, learning_starts=10,
                    policy_kwargs={"net_arch": [16], "activation_fn": nn.Tanh})
    model.learn(40)
    model.save(tmp_path / "tanh.zip")
    obs = np.random.default_rng(1).uniform(-1, 1, (16, 3)).astype(np.float32)
    got = load_victim(str(tmp_path / "tanh.zip")).act(torch.as_tensor(obs)).numpy()
    np.testing.assert_allclose(got, model.predict(obs, deterministic=True)[0], atol=1e-5)


def test_victims_are_frozen_but_pass_gradients_to_the_observation():
    module = nn.Sequential(nn.Linear(3, 8), nn.ReLU(), nn.Linear(8, 2), nn.Tanh())
    space = gym.spaces.Box(-1, 1, (2,), np.float32)
    victim = ModuleVictim(module, gym.spaces.Box(-np.inf, np.inf, (3,)), space)
    victim.train()  # a victim never leaves eval mode
    assert not victim.training and not any(p.requires_grad for p in victim.parameters())
    obs = torch.randn(5, 3, requires_grad=True)
    victim.act(obs).sum().backward()
    assert obs.grad is not None and obs.grad.abs().sum() > 0
    assert all(p.grad is None for p in victim.parameters())


def test_plain_module_actions_are_rescaled_to_the_action_bounds():
    module = nn.Sequential(nn.Linear(1, 1), nn.Tanh())
    with torch.no_grad():
        module[0].weight.fill_(100.0)
        module[0].bias.zero_()
    victim = ModuleVictim(module, gym.spaces.Box(-1, 1, (1,)), gym.spaces.Box(0.0, 4.0, (1,)))
    out = victim.act(torch.tensor([[-1.0], [0.0], [1.0]])).squeeze(-1)
    torch.testing.assert_close(out, torch.tensor([0.0, 2.0, 4.0]))


def test_own_victim_checkpoint_round_trip(tmp_path):
    env = make_task("drawer-open-v3")
    actor = TanhGaussianActor(39, 4, hidden=32, layers=2)
    path = save_victim(tmp_path / "v", actor, env.observation_space, env.action_space, {"task": "drawer-open-v3"})
    victim = load_rat_victim(path)
    obs = torch.randn(10, 39)
    torch.testing.assert_close(victim.act(obs), actor(obs))
    assert victim.meta["task"] == "drawer-open-v3"
    check_compatible(victim, env)
    assert np.isinf(victim.observation_space.high[36])  # infinities survive JSON


def test_mismatched_victim_and_environment_say_exactly_what_differs(sb3_model):
    _, path = sb3_model
    with pytest.raises(RatError, match=r"observation shape \(3,\) vs \(39,\); action shape \(1,\) vs \(4,\)"):
        check_compatible(load_sb3_victim(path), make_task("drawer-open-v3"), "drawer-open-v3")


def test_unreadable_sb3_file_is_a_one_line_error(tmp_path):
    bad = tmp_path / "model.zip"
    bad.write_bytes(b"not a zip")
    with pytest.raises(RatError, match="not a readable Stable-Baselines3 model"):
        load_victim(str(bad))
    with pytest.raises(RatError, match="no victim at"):
        load_victim(str(tmp_path / "missing"))


def test_the_foreign_victims_script_trains_saves_and_keeps_an_sb3_agent(tmp_path, capsys):
    from benchmark_scripts import load

    foreign = load("foreign_victims")
    args = ["--only", "door-close-v3-sac", "--steps", "200", "--eval-every", str(10**6), "--out", str(tmp_path)]
    record = foreign.main(args)["door-close-v3-sac"]
    assert record["trained_steps"] == 200 and record["episodes"] == 20 and 0.0 <= record["clean_success"] <= 1.0
    from rat.victims import load_victim

    victim = load_victim(str(tmp_path / "door-close-v3-sac.zip"))  # read as a user's file would be
    assert victim.observation_space.shape == (39,) and victim.meta["source"] == "stable-baselines3"
    assert json.loads((tmp_path / "victims.json").read_text())["door-close-v3-sac"]["held_out"] is False
    foreign.main(args)
    assert "trained already" in capsys.readouterr().out  # a finished agent is kept
    with pytest.raises(SystemExit):
        foreign.main(["--only", "door-close-v3-ppo", "--out", str(tmp_path)])
