"""Victim training: each method runs, checkpoints, and resumes after an interruption."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from rat.agents.sac import SACConfig
from rat.checkpoint import load_checkpoint
from rat.errors import RatError
from rat.victims import load_victim, training
from rat.victims.training import VictimConfig, train_victim

TINY_BC = VictimConfig(task="drawer-close-v3", method="bc", demo_episodes=4, demo_episode_steps=100,
                       bc_updates=400, bc_batch=64, hidden=32, layers=2, eval_episodes=2, checkpoint_every=100)
TINY_SAC = VictimConfig(task="drawer-close-v3", method="sac", hidden=32, layers=2, total_steps=600, random_steps=200,
                        sac=SACConfig(batch_size=64), eval_episodes=1, checkpoint_every=250, eval_every=10**6)


class Interrupt(Exception):
    pass


def die_at_sac_update(monkeypatch, n: int):
    """Make SAC's ``n``-th update raise :class:`Interrupt` (a killed run); returns the real update."""
    real, calls = training.SAC.update, {"n": 0}

    def update_then_die(self, batch):
        calls["n"] += 1
        if calls["n"] == n:
            raise Interrupt
        return real(self, batch)

    monkeypatch.setattr(training.SAC, "update", update_then_die)
    return real


@pytest.mark.slow
def test_bc_resumes_after_interruption_and_matches_an_uninterrupted_run(tmp_path, monkeypatch):
    whole, _ = train_victim(TINY_BC, tmp_path / "whole", progress=False)

    real = training.bc_update
    calls = {"n": 0}

    def update_then_die(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] > 250:  # killed before update 300's checkpoint is written
            raise Interrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(training, "bc_update", update_then_die)
    with pytest.raises(Interrupt):
        train_victim(TINY_BC, tmp_path / "resumed", progress=False)
    _, meta = load_checkpoint(tmp_path / "resumed" / "checkpoint")
    assert meta["update"] == 200  # the last checkpoint before the interruption
    monkeypatch.setattr(training, "bc_update", real)
    resumed, _ = train_victim(TINY_BC, tmp_path / "resumed", progress=False)

    obs = torch.randn(32, 39)
    torch.testing.assert_close(load_victim(str(resumed)).act(obs), load_victim(str(whole)).act(obs))


@pytest.mark.slow
def test_sac_resumes_from_its_last_checkpoint(tmp_path, monkeypatch):
    real_update = die_at_sac_update(monkeypatch, 300)  # updates start at step 200: step 499, last checkpoint at 250
    with pytest.raises(Interrupt):
        train_victim(TINY_SAC, tmp_path / "run", progress=False)
    state, meta = load_checkpoint(tmp_path / "run" / "checkpoint")
    assert meta["step"] == 250 and state["buffer"]["meta"][0] == 250
    assert state["optimizers"]["updates"] == 250 - 200 + 1  # one update per step from step 200 on

    monkeypatch.setattr(training.SAC, "update", real_update)
    path, result = train_victim(TINY_SAC, tmp_path / "run", progress=False)
    _, meta = load_checkpoint(tmp_path / "run" / "checkpoint")
    assert meta["step"] == 600  # the loop checkpoints the finished run's last step
    assert result.episodes == 1 and path.with_suffix(".safetensors").exists()
    rows = (tmp_path / "run" / "metrics.csv").read_text().splitlines()
    assert any(r.startswith("600,") for r in rows)  # the run reached its last step


def test_sac_demo_warm_start_fills_the_buffer_with_demonstrations(tmp_path):
    cfg = replace(TINY_SAC, method="sac-demo", demo_episodes=2, demo_episode_steps=100, bc_updates=50,
                  total_steps=250, checkpoint_every=250)
    train_victim(cfg, tmp_path / "run", progress=False)
    state, _ = load_checkpoint(tmp_path / "run" / "checkpoint")
    assert state["buffer"]["meta"][0] == 200 + 250  # 2 demonstrations of 100 steps, then 250 SAC steps
    assert state["optimizers"]["updates"] > 0


def test_a_run_directory_refuses_a_different_configuration(tmp_path):
    train_victim(replace(TINY_BC, bc_updates=100), tmp_path / "run", progress=False)
    with pytest.raises(RatError, match="differs in: bc_updates"):
        train_victim(TINY_BC, tmp_path / "run", progress=False)
    # where it runs and how often it checkpoints change nothing it computes: a resume may change them
    train_victim(replace(TINY_BC, bc_updates=100, checkpoint_every=50, device="cpu"), tmp_path / "run", progress=False)


def test_bad_training_options_are_rejected():
    with pytest.raises(RatError, match="unknown victim method"):
        VictimConfig(method="magic")
    with pytest.raises(RatError, match="no scripted expert to learn from; use --method sac"):
        VictimConfig(task="Walker2d-v5", method="bc")
    with pytest.raises(RatError, match="total-steps must be positive"):
        VictimConfig(total_steps=-5)


def test_a_sac_victim_trains_on_a_locomotion_task_too(tmp_path):
    cfg = replace(TINY_SAC, task="HalfCheetah-v5", total_steps=300, random_steps=100, checkpoint_every=300)
    path, result = train_victim(cfg, tmp_path / "run", progress=False)
    victim = load_victim(str(path))
    assert victim.meta["task"] == "HalfCheetah-v5" and victim.observation_space.shape == (17,)
    assert result.episodes == 1 and np.isfinite(result.mean_return)


def test_sac_saves_its_best_evaluated_actor_and_keeps_it_across_a_resume(tmp_path, monkeypatch):
    """Evaluations at steps 250 (scored 100%) and 500 (0%): the 250 actor is the victim, not the last."""
    cfg = replace(TINY_SAC, eval_every=250, eval_every_episodes=1, eval_episodes=2)
    real_evaluate = training.evaluate
    scripted = iter([1.0, 0.0])

    def scored(policy, env, episodes, **kwargs):
        result = real_evaluate(policy, env, episodes, **kwargs)
        if episodes == cfg.eval_every_episodes:  # a periodic evaluation, not the final one
            result = replace(result, success_rate=next(scripted))
        return result

    monkeypatch.setattr(training, "evaluate", scored)
    real_update = die_at_sac_update(monkeypatch, 350)  # step 549: after the second evaluation and the 500 checkpoint
    with pytest.raises(Interrupt):
        train_victim(cfg, tmp_path / "run", progress=False)
    state, _ = load_checkpoint(tmp_path / "run" / "checkpoint")
    assert state["best"]["step"] == 250 and state["best"]["score"][0] == 1.0

    monkeypatch.setattr(training.SAC, "update", real_update)
    path, _ = train_victim(cfg, tmp_path / "run", progress=False)
    state, _ = load_checkpoint(tmp_path / "run" / "checkpoint")
    victim = load_victim(str(path))
    assert victim.meta["kept"] == "best" and victim.meta["kept_step"] == 250
    kept, learner = (training.TanhGaussianActor(39, 4, hidden=32, layers=2) for _ in range(2))
    kept.load_state_dict(state["best"]["actor"])
    learner.load_state_dict({k.removeprefix("actor."): v for k, v in state["agent"].items() if k.startswith("actor.")})
    obs = torch.randn(16, 39)
    with torch.no_grad():
        torch.testing.assert_close(victim.act(obs), kept(obs))  # Meta-World's action box is [-1, 1]
        assert not torch.allclose(victim.act(obs), learner(obs))  # the learner moved on after step 250
