"""RAT end to end on the small point environment: it learns, and a killed run resumes exactly."""

import csv
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from point_env import BESIDE, HORIZON, PointGoal, point_victim
from safetensors.torch import load_file
from scipy import stats

from rat.agents.sac import SACConfig
from rat.attacks import AttackSetup, ThreatModel, evaluate_attack
from rat.attacks.rat import RATConfig, train_rat
from rat.attacks.threat import random_delta
from rat.checkpoint import load_checkpoint
from rat.errors import RatError
from rat.preferences.pebble import PebbleConfig
from rat.preferences.reward_model import RewardModelConfig


def small_config(steps=2000, **kw):
    kw = dict(dict(adversary_hidden=64, adversary_lr=1e-3, adversary_every=20, adversary_updates=5, adversary_batch=128,
                   weighting_every=200, eval_every=500, eval_episodes=20, final_eval_episodes=50, checkpoint_every=400),
              **kw)
    return RATConfig(
        epsilon=0.1, total_steps=steps, horizon=HORIZON, **kw,
        pebble=PebbleConfig(sac=SACConfig(hidden=64, layers=2, batch_size=128, lr=1e-3, alpha_lr=1e-3, init_temperature=0.05),
                            seed_steps=200, unsupervised_steps=200, budget=200, per_round=40, feedback_every=200,
                            segment_length=10, candidates_factor=4, buffer_capacity=20_000,
                            reward=RewardModelConfig(hidden=64, layers=2, max_epochs=20, lr=1e-3)))


def setup(seed=0):
    """RAT against the point victim, to bring the goal-side point (BESIDE) about."""
    return AttackSetup(point_victim(), BESIDE, PointGoal, ThreatModel(0.1), seed=seed, progress=False)


@pytest.mark.slow
def test_rat_beats_a_random_attack_of_the_same_budget(tmp_path):
    report = train_rat(small_config(), setup(), tmp_path / "run")
    assert report.details["adversary_updates"] > 300 and report.details["weighting_updates"] > 5 and report.labels > 100
    rng = np.random.default_rng(0)
    random = evaluate_attack(point_victim(), lambda o: random_delta(rng, 4, "linf"), PointGoal(7), BESIDE, ThreatModel(0.1),
                             50, seed=2 * 10**7)
    rat_hits = round(report.attack_success_rate * 50)
    rnd_hits = round(random.result.success_rate * 50)
    p = stats.fisher_exact([[rat_hits, 50 - rat_hits], [rnd_hits, 50 - rnd_hits]], alternative="greater").pvalue
    assert rat_hits / 50 >= 0.15 and p < 0.01, f"RAT {rat_hits}/50, random {rnd_hits}/50, p={p:.2g}"
    assert report.max_perturbation <= 0.1 + 1e-9
    assert (tmp_path / "run" / "adversary.safetensors").exists() and (tmp_path / "run" / "training.png").exists()


KILLABLE = """
import sys, torch
sys.path.insert(0, {tests!r})
torch.set_num_threads(1)
from point_env import BESIDE, PointGoal, point_victim
from test_rat_training import small_config
from rat.attacks.rat import train_rat
from test_rat_training import setup
train_rat(small_config(1200), setup(), {out!r})
"""


@pytest.mark.slow
def test_a_killed_run_resumes_and_reproduces_the_finished_runs_artefacts(tmp_path):
    whole = train_rat(small_config(1200), setup(), tmp_path / "whole")

    out = tmp_path / "killed"
    script = KILLABLE.format(tests=str(Path(__file__).parent), out=str(out))

    def run_until(done) -> None:
        proc = subprocess.Popen([sys.executable, "-c", script], env={**os.environ, "PYTHONHASHSEED": "0"})
        deadline = time.time() + 300
        while not done() and time.time() < deadline and proc.poll() is None:
            time.sleep(0.01)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()

    def logged_rows() -> int:
        path = out / "metrics.csv"
        return len(path.read_text().splitlines()) - 1 if path.exists() else 0

    # killed before its first checkpoint: a restart starts afresh and keeps none of the rows it logged
    run_until(lambda: logged_rows() >= 2)
    assert logged_rows() >= 2 and not (out / "checkpoint.json").exists(), "not killed before the first checkpoint"
    # killed after a checkpoint: a restart continues from it
    run_until(lambda: (out / "checkpoint.json").exists())
    assert (out / "checkpoint.json").exists() and not (out / "report.json").exists(), "the run was not cut short"

    resumed = train_rat(small_config(1200), setup(), out)
    a, b = load_file(tmp_path / "whole" / "adversary.safetensors"), load_file(out / "adversary.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert (resumed.attack_success_rate, resumed.labels) == (whole.attack_success_rate, whole.labels)
    for key in ("queries_asked", "adversary_updates", "weighting_updates"):
        assert resumed.details[key] == whole.details[key], key

    def metrics(run):
        with open(run / "metrics.csv") as f:
            return [{k: v for k, v in row.items() if k != "steps_per_second"} for row in csv.DictReader(f)]

    assert metrics(out) == metrics(tmp_path / "whole")  # no row twice, none missing


@pytest.mark.slow
def test_imitating_the_best_intention_policy_keeps_it_scores_it_by_r_hat_and_checkpoints_it(tmp_path):
    config = small_config(1500, imitate="best", imitate_episodes=2)
    config = replace(config, pebble=replace(config.pebble, unsupervised_steps=300))  # the first round at 500
    report = train_rat(config, setup(), tmp_path / "run")
    with open(tmp_path / "run" / "metrics.csv") as f:
        rows = [r for r in csv.DictReader(f) if r.get("imitated_step")]
    # every evaluation once π_θ learns from r̂; at 500 it is still the pre-training explorer, never kept
    assert [int(float(r["step"])) for r in rows] == [1000, 1500]
    assert all(1000 <= float(r["imitated_step"]) <= float(r["step"]) for r in rows)
    state, _ = load_checkpoint(tmp_path / "run" / "checkpoint")
    assert int(state["best"]["step"]) == int(float(rows[-1]["imitated_step"]))
    assert report.details["adversary_updates"] > 0
    with open(tmp_path / "run" / "metrics.csv") as f:
        saturated = [float(r["adversary_saturation"]) for r in csv.DictReader(f) if r.get("adversary_saturation")]
    assert saturated and all(0.0 <= x <= 1.0 for x in saturated)  # logged after every adversary phase
    with pytest.raises(RatError, match="imitate must be current or best"):
        small_config(imitate="peak")


@pytest.mark.slow
def test_a_refining_run_saves_pi_theta_beside_the_adversary_and_reports_the_networks_attack_beside(tmp_path):
    from rat.attacks.saved import adversary_function, load_adversary, load_rat_attack
    from rat.checkpoint import save_checkpoint

    config = small_config(1000, refine_steps=10, select="reward", eval_episodes=5, final_eval_episodes=10)
    report = train_rat(config, setup(), tmp_path / "run")
    assert 0.0 <= report.details["network_attack_success_rate"] <= 1.0 and "network's Δ alone" in report.summary()
    assert 0.0 <= report.details["refined_gap"] < 2 * 2 ** 0.5 and "gap left to π_θ's actions" in report.summary()
    assert report.max_perturbation <= 0.1 + 1e-9
    state, meta = load_checkpoint(tmp_path / "run" / "adversary")
    assert meta["rat"]["refine_steps"] == 10 and set(state["intention"]) >= {"trunk.0.weight"}
    assert set(state["critic"]) >= {"q1.0.weight", "q2.0.weight"}  # and its critic, for refine-loss q
    # the kept adversary is saved with the π_θ it imitated: a snapshot's own, or the last one's
    step = report.details["selected_step"]
    imitated = load_checkpoint(tmp_path / "run" / (f"snapshots/adversary-{step}" if step < 1000 else "adversary-last"))[0]
    assert all(torch.equal(state["intention"][k], imitated["intention"][k]) for k in state["intention"])
    assert torch.equal(state["adversary"]["policy.trunk.0.weight"], imitated["adversary"]["policy.trunk.0.weight"])
    pi_500, pi_1000 = (load_checkpoint(tmp_path / "run" / "snapshots" / f"adversary-{n}")[0]["intention"]
                       for n in (500, 1000))
    assert not torch.equal(pi_500["trunk.0.weight"], pi_1000["trunk.0.weight"])  # each snapshot holds its own
    # a snapshot loads as itself (`rat attack eval RUN/snapshots/adversary-500`): its adversary, its π_θ, the run's metadata
    from rat.attacks.saved import load_saved

    snapshot = load_checkpoint(tmp_path / "run" / "snapshots" / "adversary-500")[0]["adversary"]
    adversary_500, imitated_500, meta_500 = load_saved(tmp_path / "run" / "snapshots" / "adversary-500.json")
    assert meta_500["snapshot_step"] == 500 and meta_500["rat"] == meta["rat"] and "snapshot_step" not in meta
    assert all(torch.equal(adversary_500.state_dict()[k], snapshot[k]) for k in snapshot)
    assert torch.equal(imitated_500.actor.state_dict()["trunk.0.weight"], pi_500["trunk.0.weight"])
    # ... before its run has finished (its own metadata), and as written before snapshots kept more than their step
    import shutil

    (tmp_path / "running" / "snapshots").mkdir(parents=True)
    for suffix in (".json", ".safetensors"):
        shutil.copy(tmp_path / "run" / "snapshots" / f"adversary-500{suffix}", tmp_path / "running" / "snapshots")
    assert load_saved(tmp_path / "running" / "snapshots" / "adversary-500")[2] == meta_500
    save_checkpoint(tmp_path / "run" / "snapshots" / "adversary-old", "adversary-snapshot",
                    load_checkpoint(tmp_path / "run" / "snapshots" / "adversary-500")[0], {"step": 500})
    with pytest.raises(RatError, match="lacks target, epsilon, norm: it was written by an unreleased version"):
        load_saved(tmp_path / "run" / "snapshots" / "adversary-old")  # a snapshot of the old layout: its step alone
    for suffix in (".json", ".safetensors"):  # not a snapshot the run took: gone before it resumes below
        (tmp_path / "run" / "snapshots" / f"adversary-old{suffix}").unlink()
    # a run written before a setting existed resumes while that setting is at its default, and only then
    config_path = tmp_path / "run" / "config.json"
    saved = __import__("json").loads(config_path.read_text())
    del saved["rat"]["refine_lr"]  # default now
    config_path.write_text(__import__("json").dumps(saved))
    assert train_rat(config, setup(), tmp_path / "run").steps == 1000
    del saved["rat"]["refine_steps"]  # 10 now, not the default
    config_path.write_text(__import__("json").dumps(saved))
    with pytest.raises(RatError, match="refine_steps"):
        train_rat(config, setup(), tmp_path / "run")
    victim, obs = point_victim(), np.array([0.1, 0.0, 0.15, 0.02])  # the victim's action not clamped here
    network = load_rat_attack(tmp_path / "run", victim, refine_steps=0)
    adversary, _ = load_adversary(tmp_path / "run")
    np.testing.assert_allclose(network(obs), adversary_function(adversary)(obs))  # 0 steps: the network's Δ
    with pytest.raises(RatError, match="refines 0 steps; give --refine-steps"):
        load_rat_attack(tmp_path / "run", victim, refine_steps=0, refine_loss="q")  # not silently ignored
    with pytest.raises(RatError, match="refines 0 steps; give --refine-steps"):
        load_rat_attack(tmp_path / "run", victim, refine_steps=0, switch_gap=0.5)  # nor is l2-or-q's threshold
    assert not np.allclose(load_rat_attack(tmp_path / "run", victim)(obs), network(obs))  # as configured: refined
    # a run's other saved adversary loads as itself, not as the run's kept one
    from rat.attacks.base import load_attack

    other = {k: v + 0.5 for k, v in state["adversary"].items()}
    save_checkpoint(tmp_path / "run" / "adversary-last", "adversary", {"adversary": other,
                                                                        "intention": state["intention"]}, meta)
    last, _ = load_attack(tmp_path / "run" / "adversary-last.json", victim)
    np.testing.assert_allclose(last(obs), load_rat_attack(tmp_path / "run" / "adversary-last", victim)(obs))
    assert not np.allclose(load_attack(tmp_path / "run" / "adversary-last", victim)[0](obs),
                           load_attack(tmp_path / "run", victim)[0](obs))
    # refined by π_θ's critic: its own, saved with it; a file saved without one (an unreleased layout) says what to do
    by_q = load_rat_attack(tmp_path / "run", victim, refine_loss="q")(obs)
    assert not np.allclose(by_q, network(obs)) and not np.allclose(by_q, load_rat_attack(tmp_path / "run", victim)(obs))
    save_checkpoint(tmp_path / "run" / "adversary", "adversary", {"adversary": state["adversary"],
                                                                   "intention": state["intention"]}, meta)
    with pytest.raises(RatError, match="refine-loss 'q' climbs π_θ's critic, and '.*' saved none"):
        load_rat_attack(tmp_path / "run", victim, refine_loss="q")
    # an adversary saved without π_θ (by an older version) still attacks, but cannot be refined, and says what to do
    save_checkpoint(tmp_path / "run" / "adversary", "adversary", {"adversary": state["adversary"]}, meta)
    np.testing.assert_allclose(load_rat_attack(tmp_path / "run", victim, refine_steps=0)(obs), network(obs))
    with pytest.raises(RatError, match="did not save the intention policy"):
        load_rat_attack(tmp_path / "run", victim)


@pytest.mark.parametrize("ablation, victim_acts, weighted", [("no-combined", False, True), ("no-weighting", True, False)])
def test_each_ablation_removes_its_own_component_only(tmp_path, ablation, victim_acts, weighted):
    report = train_rat(small_config(600, ablation=ablation), setup(), tmp_path / "run")
    with open(tmp_path / "run" / "metrics.csv") as f:
        switches = [float(r["switch_step"]) for r in csv.DictReader(f) if r.get("switch_step")]
    assert switches and any(h > 0 for h in switches) == victim_acts  # h = 0: π_θ acts from the first step
    assert report.details["adversary_updates"] > 0 and (report.details["weighting_updates"] > 0) == weighted






def test_an_oracle_run_of_the_cpu_preset_keeps_the_last_adversary_and_imitates_the_live_intention_policy():

    from rat.attacks.rat import RAT
    from rat.experiments.presets import rat_config

    config = rat_config("cpu", target="opposite")  # scores snapshots and π_θ with r̂, which an oracle run never learns
    assert (config.select, config.imitate) == ("reward", "best")
    manipulation = rat_config("cpu", target="reach")  # docs/notes/strength-log.md: measured on the SAC faucet victim's row
    assert (manipulation.select, manipulation.imitate, manipulation.refine_steps) == ("last", "current", 50)
    assert (manipulation.refine_loss, config.refine_loss) == ("l2-or-q", "l2")  # docs/notes/strength-log.md: l2, and q where l2 falls short
    assert manipulation.pebble.max_episodes == 20 and manipulation.pebble.reward.normalize_inputs
    paper = rat_config("paper", target="reach")  # the paper's settings stay one preset away
    assert (paper.select, paper.imitate, paper.refine_steps, paper.refine_loss, paper.pebble.max_episodes) == \
        ("last", "current", 0, "l2", 100)
    assert not paper.pebble.reward.normalize_inputs
    oracle = RAT.configure(replace(setup(), reward="oracle"), config)
    assert oracle.pebble.oracle and (oracle.select, oracle.imitate) == ("last", "current")
    labelled = RAT.configure(setup(), config)
    assert not labelled.pebble.oracle and (labelled.select, labelled.imitate) == ("reward", "best")


def test_rat_against_a_sequence_victim_trains_on_each_state_in_the_context_the_victim_had_there(tmp_path, monkeypatch):

    import rat.attacks.rat as rat_module

    pytest.importorskip("transformers", reason="pip install 'rat[dt]' (the dev extra has it)")
    from point_env import point_dt_victim

    victim = point_dt_victim(tmp_path / "dt")
    before = {k: v.clone() for k, v in victim.state_dict().items()}
    cfg = replace(small_config(700), weighting_every=100, horizon=None)  # H: the environment's time limit
    contexts = []  # whether each inner and outer step was given the victim's contexts
    for name in ("adversary_update", "weighting_update"):
        def spy(*args, _step=getattr(rat_module, name), **kwargs):
            contexts.append(args[-1] is not None)  # the trainer passes the (outer) states' contexts last
            return _step(*args, **kwargs)
        monkeypatch.setattr(rat_module, name, spy)
    report = train_rat(replace(cfg, refine_steps=5),  # the final attack refines Δ in each episode's context
                       AttackSetup(victim, BESIDE, PointGoal, ThreatModel(0.1), progress=False), tmp_path / "run")
    assert report.details["adversary_updates"] > 0 and report.details["weighting_updates"] > 0
    assert "network_attack_success_rate" in report.details and report.details["refined_gap"] >= 0
    assert len(contexts) == report.details["adversary_updates"] + report.details["weighting_updates"]
    assert all(contexts)  # both levels see each state in the context the victim had there
    assert report.max_perturbation <= 0.1 + 1e-9
    assert all(torch.equal(before[k], v) for k, v in victim.state_dict().items())  # the victim never changes
    assert __import__("json").loads((tmp_path / "run" / "config.json").read_text())["rat"]["horizon"] == HORIZON

    state, _ = load_checkpoint(tmp_path / "run" / "checkpoint")
    buffer = state["learner"]["buffer"]
    contexts = victim.unpack_context(torch.as_tensor(state["contexts"]))
    assert len(state["contexts"]) == len(buffer["obs"]) == 700
    steps = contexts.timesteps[:, -1].long().numpy()
    assert steps[0] == 0 and set(np.diff(steps)) <= {1, -(HORIZON - 1)}  # each state knows its episode step
    inside = np.flatnonzero(steps[1:] > 0) + 1  # states with a previous step in their episode
    seen = contexts.states[inside, -1].numpy()  # the previous state, as the victim saw it
    gap = np.abs(seen - buffer["obs"][inside - 1]).max(-1)
    assert (gap <= 0.1 + 1e-6).all() and (gap > 0).all()  # perturbed, within ε, every one (π_θ's steps too)
    np.testing.assert_allclose(contexts.actions[inside, -1].numpy(), buffer["action"][inside - 1], atol=1e-6)
    fresh = np.flatnonzero(steps == 0)
    assert (contexts.mask[fresh].sum(1) == 0).all() and (contexts.mask[inside, -1] == 1).all()
    rtg = contexts.returns_to_go[:, -1].numpy()
    assert np.allclose(rtg[fresh], -2.0) and (np.diff(rtg)[inside - 1] != 0).all()  # lowered by each step's reward
