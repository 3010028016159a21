"""Robust training on the point environment: the phases alternate, the buffer holds what the agent saw, the
worst-case term moves the actor alone, and a killed run resumes where it was."""

import copy

import numpy as np
import pytest
import torch
from point_env import BESIDE, PointGoal, point_sac_victim, point_victim
from safetensors.torch import load_file
from test_rat_training import small_config

from rat.agents.sac import SAC, SACConfig
from rat.attacks.rl import PPOConfig
from rat.attacks.threat import ThreatModel
from rat.errors import RatError
from rat.robust import RobustConfig, RobustTrainer, prepare_robust, train_robust
from rat.robust.terms import Anchor, WorstCaseValue

EPS = ThreatModel(0.1)


def config(method="atla", **kw):
    return RobustConfig(**dict(dict(method=method, agent_steps=400, phase_steps=200, adversary_phase_steps=200,
                                    first_adversary_steps=400, critic_warmup=200, eval_every=10**6, eval_episodes=5,
                                    final_eval_episodes=10, checkpoint_every=200,
                                    sac=SACConfig(hidden=64, layers=2, batch_size=64, lr=1e-3)), **kw))


def adversary_settings(method):
    if method.startswith("rat"):
        return small_config(400)
    return PPOConfig(learning_rate=1e-3, batch_size=100, n_steps=200, n_epochs=2, hidden=32, layers=1)


def trainer_for(cfg, out):
    _, trainer, _ = prepare_robust(cfg, point_sac_victim(updates=200), BESIDE, PointGoal, EPS, out,
                                   adversary_settings(cfg.method), describe={"task": "point"}, progress=False)
    return trainer


def flat(module) -> torch.Tensor:
    return torch.nn.utils.parameters_to_vector(module.parameters()).detach().clone()


def test_the_phases_alternate_and_each_moves_only_its_own_weights(tmp_path):
    trainer = trainer_for(config("atla"), tmp_path / "run")
    ppo = trainer.adversary.trainer.model.policy
    phases, moved = [trainer.phase], {}
    while not trainer.finished:
        before = trainer.phase, flat(trainer.agent.actor), flat(trainer.agent.critic), flat(ppo), flat(trainer.victim.policy)
        trainer.advance()
        after = flat(trainer.agent.actor), flat(trainer.agent.critic), flat(ppo), flat(trainer.victim.policy)
        if trainer.phase != phases[-1]:
            phases.append(trainer.phase)
            if trainer.phase == "adversary" and before[0] == "agent":  # the agent handed to the adversary's victim
                assert torch.equal(after[3], after[0])
            continue
        changed = {name: not torch.equal(b, a) for name, b, a in zip(("actor", "critic", "adversary", "victim"),
                                                                      before[1:], after)}
        for name, did in changed.items():
            moved.setdefault((before[0], name), set()).add(did)
    assert phases == ["warm-up", "adversary", "agent", "adversary", "agent", "adversary", "done"]
    assert trainer.counters["adversary_phases"] == 3 and trainer.counters["agent_phases"] == 2
    assert trainer.agent_steps == 400 and trainer.warmup_steps == 200
    # within a phase: the warm-up trains the critic alone, the agent's phase the agent, the adversary's the adversary
    assert moved[("warm-up", "actor")] == {False} and True in moved[("warm-up", "critic")]
    assert moved[("agent", "adversary")] == {False} and moved[("agent", "victim")] == {False}
    assert True in moved[("agent", "actor")] and True in moved[("agent", "critic")]
    assert moved[("adversary", "actor")] == {False} and moved[("adversary", "critic")] == {False}
    assert moved[("adversary", "victim")] == {False} and moved[("adversary", "adversary")] == {True}


def test_the_control_trains_the_agent_alone_on_clean_observations(tmp_path):
    trainer = trainer_for(config("none"), tmp_path / "run")
    assert trainer.adversary is None
    phases, actor = [trainer.phase], flat(trainer.agent.actor)
    while not trainer.finished:
        trainer.advance()
        phases += [trainer.phase] * (trainer.phase != phases[-1])
    assert phases == ["warm-up", "agent", "done"]
    assert trainer.counters["adversary_phases"] == 0 and trainer.counters["agent_updates"] > 300
    assert not torch.equal(flat(trainer.agent.actor), actor)
    n = len(trainer.buffer)
    np.testing.assert_array_equal(trainer.buffer.obs[:n], trainer.true_obs[:n])  # nothing perturbed what it saw


def test_the_agents_buffer_holds_the_perturbed_observations_it_was_shown(tmp_path):
    trainer = trainer_for(config("atla"), tmp_path / "run")
    while trainer.phase != "agent":
        trainer.advance()
    wrapper, checked = trainer.env, 0
    while trainer.phase == "agent":
        seen, true = trainer.obs, wrapper._last_true
        trainer.advance()
        if seen is None:  # the episode's first step: its observation came from the reset inside advance()
            continue
        i = trainer.buffer.last_index
        np.testing.assert_allclose(trainer.buffer.obs[i], seen, rtol=0, atol=1e-6)
        np.testing.assert_allclose(trainer.true_obs[i], true, rtol=0, atol=1e-6)  # beside it, the true s under s̃
        assert np.abs(seen - true).max() > 1e-4
        true_next = wrapper._last_true
        shown_next = trainer.buffer.next_obs[i]
        assert np.abs(shown_next - true_next).max() <= 0.1 + 1e-6  # inside the ε-ball of the true next state
        assert np.abs(shown_next - true_next).max() > 1e-4  # and perturbed
        if trainer.obs is not None:  # s̃ₜ₊₁ is the next step's s̃ₜ: the same draw, not a fresh one
            np.testing.assert_allclose(shown_next, trainer.obs, rtol=0, atol=1e-6)
        checked += 1
    assert checked > 150


def test_the_worst_case_term_moves_the_actors_gradient_and_not_the_critics():
    torch.manual_seed(0)
    from rat.agents.sac import SAC

    agent = SAC(4, 2, SACConfig(hidden=32, layers=2, batch_size=32))
    term = WorstCaseValue(4, 2, EPS, hidden=32, layers=2)
    term.kappa = 0.5
    batch = {"obs": torch.randn(32, 4), "action": torch.rand(32, 2) * 2 - 1, "reward": torch.randn(32),
             "next_obs": torch.randn(32, 4), "terminated": torch.zeros(32)}
    grads = {}
    for name, extra in (("without", None), ("with", term)):
        state = {k: v.clone() for k, v in agent.state_dict().items()}  # the same start for both
        optimizers = copy.deepcopy(agent.optimizer_state())
        rng = torch.get_rng_state()
        agent.update(batch, actor_extra=extra)
        grads[name] = (flat(agent.actor), flat(agent.critic))
        q_w = flat(term.q)
        agent.load_state_dict(state)
        agent.load_optimizer_state(optimizers)
        torch.set_rng_state(rng)
    assert torch.equal(grads["with"][1], grads["without"][1])  # the critic's step is the same
    assert not torch.equal(grads["with"][0], grads["without"][0])  # the actor's is not
    assert torch.equal(q_w, flat(term.q))  # and Q_w is moved only by its own Bellman update


def test_the_warm_up_explores_around_the_starting_actor_and_the_anchor_pulls_back_to_it(tmp_path):
    cfg = config("rat-wocar", wocar_critic="worst-case", wocar_kappa=0.0, warmup_noise=0.3, anchor=1.0)
    _, trainer, _ = prepare_robust(cfg, point_sac_victim(updates=200), BESIDE, PointGoal, EPS, tmp_path / "run",
                                   None, describe={"task": "point"}, progress=False)
    assert trainer.term is None  # κ = 0: plain fine-tuning, no worst-case Q to learn
    assert not trainer.agent.config.learnable_temperature  # fixed at finetune_temperature
    assert trainer.agent.alpha.item() == pytest.approx(0.001)
    while trainer.phase == "warm-up":
        trainer.advance()
    n = len(trainer.buffer)
    obs, actions = (torch.as_tensor(a[:n], dtype=torch.float32) for a in (trainer.buffer.obs, trainer.buffer.action))
    with torch.no_grad():
        spread = (actions - trainer.anchor.start(obs)).std().item()
    assert 0.2 < spread < 0.35  # σ = 0.3 around μ₀ (less where clipped), not the actor's own tiny spread
    start = trainer.anchor.start
    with torch.no_grad():  # move the agent's actor away from μ₀, then step on the anchor alone
        for p in trainer.agent.actor.parameters():
            p.add_(0.05 * torch.randn_like(p))
    distance = lambda: ((trainer.agent.actor(obs) - start(obs)) ** 2).sum(-1).mean().item()  # noqa: E731
    before = distance()
    optimizer = torch.optim.SGD(trainer.agent.actor.parameters(), lr=1e-3)
    for _ in range(20):
        action, _ = trainer.agent.actor.sample(obs)
        loss = trainer.anchor(obs, action, obs).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert distance() < 0.8 * before


def test_the_anchor_takes_the_starting_actor_at_the_true_observation():
    actor = point_sac_victim(updates=200).policy
    agent = SAC(4, 2, SACConfig(hidden=32, layers=2))
    anchor = Anchor(copy.deepcopy(actor), agent.critic, weight=1.0)
    true_obs = torch.randn(64, 4)
    seen = true_obs + 0.1 * torch.sign(torch.randn(64, 4))
    with torch.no_grad():
        answer = actor(true_obs)
    assert torch.all(anchor(seen, answer, true_obs) == 0)  # the true state's answer, wherever the agent looked
    with torch.no_grad():
        assert torch.all(anchor(seen, actor(seen), true_obs) > 0)  # not its answer to what the agent saw


class Interrupt(Exception):
    pass


def test_a_run_killed_mid_phase_resumes_where_it_was(tmp_path, monkeypatch):
    cfg = config("rat-wocar", wocar_critic="worst-case", checkpoint_every=100)
    whole = train_robust(cfg, point_sac_victim(updates=200), BESIDE, PointGoal, EPS, tmp_path / "whole",
                         describe={"task": "point"}, progress=False)
    real, calls = RobustTrainer._update, {"n": 0}

    def dies_midway(self, actor):
        calls["n"] += 1
        if calls["n"] == 430:  # the agent's second phase, between its checkpoints
            raise Interrupt
        return real(self, actor)

    monkeypatch.setattr(RobustTrainer, "_update", dies_midway)
    with pytest.raises(Interrupt):
        train_robust(cfg, point_sac_victim(updates=200), BESIDE, PointGoal, EPS, tmp_path / "killed",
                     describe={"task": "point"}, progress=False)
    assert (tmp_path / "killed" / "checkpoint.json").exists() and not (tmp_path / "killed" / "report.json").exists()
    monkeypatch.setattr(RobustTrainer, "_update", real)
    resumed = train_robust(cfg, point_sac_victim(updates=200), BESIDE, PointGoal, EPS, tmp_path / "killed",
                           describe={"task": "point"}, progress=False)
    a, b = load_file(tmp_path / "whole" / "victim.safetensors"), load_file(tmp_path / "killed" / "victim.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    for key in ("agent_steps", "agent_updates", "agent_phases", "clean_return"):
        assert resumed[key] == whole[key], key


@pytest.mark.parametrize("kw, message", [
    (dict(method="atla-plus"), "unknown robust-training method 'atla-plus'"),
    (dict(init="warm"), "init must be one of finetune, scratch"),
    (dict(agent_steps=-5), "agent-steps must be positive"),
    (dict(first_adversary_steps=0), "needs an adversary trained first"),
])
def test_bad_settings_are_named(kw, message):
    with pytest.raises(RatError, match=message):
        config(**kw)


def test_a_victim_that_is_not_a_sac_actor_cannot_be_fine_tuned(tmp_path):
    with pytest.raises(RatError, match="pass --init scratch"):
        prepare_robust(config("atla"), point_victim(), BESIDE, PointGoal, EPS, tmp_path / "run",
                       adversary_settings("atla"), progress=False)


def test_the_robust_agent_loads_as_a_victim(tmp_path):
    from rat.victims import load_victim

    cfg = config("rat-wocar", wocar_critic="worst-case", agent_steps=200, eval_every=200)
    report = train_robust(cfg, point_sac_victim(updates=200), BESIDE, PointGoal, EPS, tmp_path / "run",
                          describe={"task": "point"}, progress=False)
    agent = load_victim(str(tmp_path / "run"))
    assert agent.meta["method"] == "robust-rat-wocar" and agent.meta["robust"]["init"] == "finetune"
    assert report["agent_steps"] == 200 and (tmp_path / "run" / "training.png").stat().st_size > 0
    obs = torch.randn(16, 4)
    saved = load_file(tmp_path / "run" / "victim.safetensors")
    assert not torch.equal(agent.act(obs), point_sac_victim(updates=200).act(obs))  # fine-tuned, not the start
    assert saved  # weights, in safetensors


@pytest.mark.parametrize("args, message", [
    (["--target", "opposite"], "needs a target of the victim's own environment"),
    (["--set", "agent_steps=-1"], "agent-steps must be positive"),
    (["--victim", "zoo:nowhere-v3@sac"], "no zoo victim 'nowhere-v3@sac'"),
    (["--method", "rat-wocar", "--wocar-critic", "worst-case", "--adversary-set", "adversary_lr=1e-3"],
     "trains no adversary; drop --adversary-set"),
])
def test_bad_robust_commands_end_in_one_line_and_exit_2(tmp_path, capsys, args, message):
    from rat.cli import main

    assert main(["robust", "train", *args, "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert not (tmp_path / "run").exists()  # nothing written


def test_robust_eval_of_an_unfinished_run_says_how_to_finish_it(tmp_path, capsys):
    from rat.cli import main

    assert main(["robust", "eval", str(tmp_path)]) == 2
    assert "finish it with the same `rat robust train ... --out` command" in capsys.readouterr().err


@pytest.mark.slow
def test_a_rat_atla_agent_beats_the_undefended_victim_under_a_fixed_attack(tmp_path):
    """The fixed attack: a RAT attack trained against the undefended victim and frozen; the robust agent trains
    against its own adversary and never sees it (benchmarks/robust_point.py: the point environment's recipe,
    the cpu preset's anchor)."""
    from benchmark_scripts import load
    from scipy import stats

    bench = load("robust_point")
    attack = bench.fixed_attack(0, tmp_path / "attack")
    trainer = bench.robust_agent("rat-atla", 0, {}, tmp_path / "run")
    assert trainer.counters["agent_updates"] >= 3500 and trainer.counters["adversary_phases"] == 11
    robust, undefended = bench.attacked(trainer.current_agent(), attack), bench.attacked(point_sac_victim(), attack)
    n = bench.EPISODES
    p = stats.ttest_ind_from_stats(robust["return"], robust["std"], n, undefended["return"], undefended["std"], n,
                                   equal_var=False, alternative="greater").pvalue
    assert robust["return"] >= undefended["return"] + 1.0 and p < 0.01, f"{robust}, {undefended}, p={p:.2g}"


def test_a_checkpoint_of_an_unreleased_layout_is_refused_in_one_line(tmp_path):
    import json

    cfg = config("rat-wocar", wocar_critic="worst-case", agent_steps=200, critic_warmup=200)
    run, trainer, loop = prepare_robust(cfg, point_sac_victim(updates=200), BESIDE, PointGoal, EPS, tmp_path / "run",
                                        describe={"task": "point"}, progress=False)
    while trainer.step < 100:
        trainer.advance()
    loop.checkpoint()
    path = tmp_path / "run" / "checkpoint.json"
    record = json.loads(path.read_text())
    del record["meta"]["seconds"]  # as a checkpoint written before its time was recorded
    path.write_text(json.dumps(record))
    _, _, again = prepare_robust(cfg, point_sac_victim(updates=200), BESIDE, PointGoal, EPS, tmp_path / "run",
                                 describe={"task": "point"}, progress=False)
    with pytest.raises(RatError, match="lacks 'seconds': an unreleased version of rat wrote it; train into a new --out"):
        again.resume()
