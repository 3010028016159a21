"""Making Decision Transformer victims: expert data, training that learns and resumes exactly, the hub layout, the zoo."""

import csv
import json
import shutil

import numpy as np
import pytest
import torch
from scipy import stats

pytest.importorskip("transformers", reason="pip install 'rat[dt]' (the dev extra has it)")

from rat.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from rat.envs import make_task  # noqa: E402
from rat.errors import RatError  # noqa: E402
from rat.victims import load_victim  # noqa: E402
from rat.victims.base import ModuleVictim  # noqa: E402
from rat.victims.dt_training import (  # noqa: E402
    DTConfig,
    DTTrainer,
    ExpertData,
    collect_expert_data,
    d4rl_score,
    train_dt,
)

TASK = "HalfCheetah-v5"


def linear_expert(seed=0):
    """A deterministic stand-in for an expert: a fixed random linear map, squashed."""
    torch.manual_seed(seed)
    env = make_task(TASK)
    return ModuleVictim(torch.nn.Sequential(torch.nn.Linear(17, 6), torch.nn.Tanh()), env.observation_space,
                        env.action_space, name="linear-expert")


def tiny(**kw):
    return DTConfig(task=TASK, hidden=32, layers=1, context_length=5, batch_size=32, lr=1e-3, warmup_steps=20,
                    dropout=0.0, eval_every=10_000, eval_episodes=1, checkpoint_every=100, **kw)


@pytest.fixture(scope="module")
def data_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "expert-data.safetensors"
    collect_expert_data(linear_expert(), TASK, episodes=3, seed=0, noise=0.1).save(path)
    return path


def test_expert_data_are_the_experts_episodes_and_load_back_without_code(data_file, tmp_path):
    data = ExpertData.load(data_file)
    assert data.obs.shape == (3000, 17) and data.actions.shape == (3000, 6) and list(data.episode_starts) == [0, 1000, 2000]
    assert data.meta["task"] == TASK and data.meta["expert"] == "linear-expert" and data.meta["noise"] == 0.1
    with torch.no_grad():
        clean = linear_expert().act(torch.as_tensor(data.obs)).numpy()
    noise = data.actions - clean
    assert 0.05 < noise.std() < 0.15 and np.abs(data.actions).max() <= 1.0  # the expert's action, noised, clipped
    np.testing.assert_allclose(data.episode_returns.sum(), data.rewards.sum(), rtol=1e-5)
    (tmp_path / "bad.safetensors").write_bytes(b"\x00" * 64)
    with pytest.raises(RatError, match="not expert data written by rat"):
        ExpertData.load(tmp_path / "bad.safetensors")


def test_a_decision_transformer_learns_the_experts_actions_and_ships_in_the_hub_layout(data_file, tmp_path, monkeypatch):
    config = tiny(data=str(data_file), updates=400)
    directory, result = train_dt(config, tmp_path / "run", progress=False)
    with open(tmp_path / "run" / "metrics.csv") as f:
        losses = [float(r["action_loss"]) for r in csv.DictReader(f) if r.get("action_loss")]
    assert len(losses) == 4 and losses[-1] < 0.5 * losses[0], losses  # the update path ran and the loss fell
    meta = json.loads((directory / "rat_dt.json").read_text())
    assert meta["task"] == TASK and meta["context_length"] == 5 and meta["data"]["transitions"] == 3000
    assert meta["target_return"] == pytest.approx(float(ExpertData.load(data_file).episode_returns.max()))
    assert meta["d4rl_score"] == pytest.approx(d4rl_score(TASK, result.mean_return), abs=0.1)

    victim = load_victim(str(directory))  # a folder in the hub's layout
    assert load_victim(str(tmp_path / "run")).meta["task"] == TASK  # or the run that made it
    untrained = DTTrainer(config, ExpertData.load(data_file), np.random.default_rng(0)).victim()
    env, expert = make_task(TASK, seed=99), linear_expert()
    errors = {"trained": [], "untrained": []}
    for name, v in (("trained", victim), ("untrained", untrained)):  # fresh episodes, the victim in control
        obs, _ = env.reset(seed=99)
        context = v.initial_context()
        for _ in range(60):
            o = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
            with torch.no_grad():
                action, target = v.act(o, context), expert.act(o)
            errors[name].append(float(((action - target) ** 2).mean()))
            obs, reward, *_ = env.step(action[0].numpy())
            context = v.update_context(context, o, action, torch.tensor([reward]))
    assert np.mean(errors["trained"]) < 0.5 * np.mean(errors["untrained"])
    assert stats.mannwhitneyu(errors["trained"], errors["untrained"], alternative="less").pvalue < 0.01

    zoo = tmp_path / "zoo"
    shutil.copytree(directory, zoo / "dt" / "halfcheetah-v5")
    monkeypatch.setenv("RAT_ZOO", str(zoo))
    from_zoo = load_victim("zoo:dt/halfcheetah-v5")
    obs = torch.randn(3, 17)
    torch.testing.assert_close(from_zoo.act(obs), victim.act(obs))
    from rat.victims.zoo import zoo_dt_victims

    assert zoo_dt_victims(zoo) == {TASK: "dt/halfcheetah-v5"}
    with pytest.raises(RatError, match="no zoo Decision Transformer 'dt/hopper-v5'.*zoo:dt/halfcheetah-v5"):
        load_victim("zoo:dt/hopper-v5")


def test_training_resumes_exactly_from_a_checkpoint(data_file, tmp_path):
    config = tiny(data=str(data_file), updates=100)
    data = ExpertData.load(data_file)
    from rat.runs import seed_everything

    first = DTTrainer(config, data, seed_everything(0))
    for _ in range(30):
        first.advance()
    save_checkpoint(tmp_path / "checkpoint", first.kind, first.state_dict(), {"step": first.step})
    first.losses = []
    for _ in range(20):
        first.advance()
    second = DTTrainer(config, data, seed_everything(123))  # another seed: everything must come from the checkpoint
    state, meta = load_checkpoint(tmp_path / "checkpoint", "dt-run")
    second.load_state_dict(state, meta)
    for _ in range(20):
        second.advance()
    assert second.step == first.step == 50 and second.losses == first.losses
    assert second.scheduler.get_last_lr() == first.scheduler.get_last_lr()


def test_bad_dt_options_are_one_line(tmp_path, data_file):
    with pytest.raises(RatError, match="one of the two"):
        train_dt(tiny(), tmp_path / "a", progress=False)
    with pytest.raises(RatError, match="no expert data at"):
        train_dt(tiny(data=str(tmp_path / "none.safetensors")), tmp_path / "b", progress=False)
    with pytest.raises(RatError, match="made for HalfCheetah-v5, Walker2d-v5"):
        DTConfig(task="drawer-open-v3")
    with pytest.raises(RatError, match="updates must be positive"):
        tiny(data=str(data_file), updates=0)
    with pytest.raises(RatError, match="data are of HalfCheetah-v5, not Walker2d-v5"):
        train_dt(DTConfig(task="Walker2d-v5", data=str(data_file), updates=1), tmp_path / "c", progress=False)
