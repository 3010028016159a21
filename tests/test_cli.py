"""The CLI, called in-process. Bad input: exit code 2 and one line on stderr naming the fix."""

import sys

import click
import gymnasium as gym
import pytest

from rat.checkpoint import save_checkpoint
from rat.cli import main
from rat.errors import RatError


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def assert_user_error(code, err, *fragments):
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rat: error: "), err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def test_listings(capsys):
    code, out, _ = run(capsys, "list", "tasks")
    assert code == 0 and "drawer-open-v3" in out and "zoo:drawer-open-v3" in out
    code, out, _ = run(capsys, "list", "targets")
    assert code == 0 and "reach" in out and "opposite" in out


def test_list_presets_prints_what_each_preset_sets(capsys):
    import json
    from dataclasses import asdict

    from rat.configs import with_values
    from rat.experiments.presets import ppo_preset, rat_config

    code, out, _ = run(capsys, "list", "presets", "--json")
    table = json.loads(out)
    assert code == 0 and set(table) == {"cpu", "paper", "smoke"}
    for preset, parts in table.items():
        for scenario, values in parts["rat"].items():
            config = rat_config(preset, target="reach" if scenario == "manipulation" else "opposite")
            assert with_values(config, values) == config  # every value printed is one the preset sets
        assert asdict(ppo_preset(preset)).items() >= parts["ppo"].items()
    assert table["cpu"]["rat"]["manipulation"]["refine_steps"] == 50 and "refine_steps" not in table["paper"]["rat"]["manipulation"]
    code, out, _ = run(capsys, "list", "presets")
    assert code == 0 and "--preset smoke" in out and "rat robust train: agent_steps=2000" in out


@pytest.mark.slow
def test_victim_eval_reports_success_with_an_interval_and_writes_a_video(capsys, tmp_path):
    video = tmp_path / "episode.mp4"
    code, out, err = run(capsys, "victim", "eval", "zoo:drawer-open-v3", "--episodes", "2", "--video", str(video),
                         "--video-episodes", "1")
    assert code == 0, err
    assert "success 100.0% (95% CI" in out
    assert video.exists() and video.stat().st_size > 10_000


def test_victim_eval_of_a_target_behaviour_runs_in_that_targets_environment(capsys):
    code, out, err = run(capsys, "victim", "eval", "zoo:drawer-open-v3", "--episodes", "1", "--target", "opposite",
                         "--json")
    assert code == 0, err
    assert '"task": "drawer-close-v3"' in out and '"target": "opposite"' in out


def test_victim_train_from_the_cli(capsys, tmp_path):
    code, out, err = run(capsys, "victim", "train", "--task", "drawer-close-v3", "--demo-episodes", "2",
                         "--bc-updates", "50", "--eval-episodes", "1", "--out", str(tmp_path / "run"))
    assert code == 0, err
    assert (tmp_path / "run" / "victim.safetensors").exists() and "clean evaluation" in out


def test_unknown_task(capsys):
    assert_user_error(*run(capsys, "victim", "train", "--task", "drawer-opne-v3")[::2], "unknown task", "rat list tasks")


def test_unknown_target(capsys):
    assert_user_error(*run(capsys, "victim", "eval", "zoo:drawer-open-v3", "--target", "fly")[::2],
                      "unknown target behaviour 'fly'", "rat list targets")


def test_victim_environment_mismatch(capsys, tmp_path):
    sb3 = pytest.importorskip("stable_baselines3")
    model = sb3.TD3("MlpPolicy", gym.make("Pendulum-v1"), learning_starts=10, policy_kwargs={"net_arch": [8]})
    model.save(tmp_path / "pendulum.zip")
    assert_user_error(*run(capsys, "victim", "eval", str(tmp_path / "pendulum.zip"), "--task", "drawer-open-v3")[::2],
                      "does not fit task 'drawer-open-v3'", "observation shape (3,) vs (39,)")


def test_corrupted_and_foreign_checkpoints(capsys, tmp_path):
    (tmp_path / "victim.json").write_text("{ not json")
    (tmp_path / "victim.safetensors").write_bytes(b"")
    assert_user_error(*run(capsys, "victim", "eval", str(tmp_path / "victim"))[::2], "corrupted")
    save_checkpoint(tmp_path / "other", "sac-run", {}, {})
    assert_user_error(*run(capsys, "victim", "eval", str(tmp_path / "other"))[::2], "not a 'victim' one")


def test_missing_optional_dependency(capsys, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # as if not installed
    assert_user_error(*run(capsys, "victim", "train", "--task", "drawer-close-v3", "--tensorboard",
                           "--out", str(tmp_path / "r"))[::2], "pip install 'rat[tensorboard]'")


def test_negative_numbers(capsys, tmp_path):
    assert_user_error(*run(capsys, "victim", "eval", "zoo:drawer-open-v3", "--episodes", "-3")[::2],
                      "--episodes must be positive")
    assert_user_error(*run(capsys, "attack", "eval", str(tmp_path), "--lockstep", "0")[::2],
                      "--lockstep must be positive")
    assert_user_error(*run(capsys, "victim", "train", "--task", "drawer-open-v3", "--bc-updates", "-1",
                           "--out", str(tmp_path / "r"))[::2], "bc-updates must be positive")


@pytest.mark.slow
def test_intention_train_reports_success_reward_quality_and_plots(capsys, tmp_path):
    out = tmp_path / "run"
    code, text, err = run(capsys, "intention", "train", "--task", "drawer-open-v3", "--target", "reach",
                          "--steps", "1000", "--seed-steps", "100", "--pretrain-steps", "300", "--budget", "40",
                          "--per-round", "20", "--every", "300", "--batch-size", "32", "--reward-epochs", "3", "--eval-every", "500",
                          "--set", "eval_episodes=2", "--set", "final_eval_episodes=3", "--set", "quality_episodes=2",
                          "--out", str(out))
    assert code == 0, err
    assert "target success of the intention policy" in text and "preference accuracy" in text
    for name in ("report.json", "reward_quality.png", "training.png", "labels.sqlite", "metrics.csv", "config.json"):
        assert (out / name).exists(), name
    from rat.reports import IntentionReport

    report = IntentionReport.read(out)
    assert report.queries_asked == 40 and report.labels == 40

    code, text, err = run(capsys, "labels", "list", str(out / "labels.sqlite"), "--show", "2")
    assert code == 0 and "40 labels, 40 queries asked in 2 rounds" in text
    code, text, _ = run(capsys, "labels", "export", str(out / "labels.sqlite"), str(tmp_path / "set.sqlite"))
    assert code == 0 and "exported 40 labels" in text
    code, text, _ = run(capsys, "labels", "import", str(tmp_path / "other.sqlite"), str(tmp_path / "set.sqlite"))
    assert code == 0 and "imported 40 labels" in text


def test_label_commands_refuse_missing_or_broken_stores(capsys, tmp_path):
    assert_user_error(*run(capsys, "labels", "list", str(tmp_path / "none.sqlite"))[::2], "no label store")
    (tmp_path / "bad.sqlite").write_bytes(b"garbage" * 200)
    assert_user_error(*run(capsys, "labels", "list", str(tmp_path / "bad.sqlite"))[::2], "not a readable label store")


def test_intention_bad_inputs(capsys, tmp_path):
    assert_user_error(*run(capsys, "intention", "train", "--budget", "-5", "--out", str(tmp_path / "a"))[::2],
                      "budget must not be negative")
    assert_user_error(*run(capsys, "intention", "train", "--strategy", "best", "--out", str(tmp_path / "b"))[::2],
                      "unknown query strategy 'best'")
    assert_user_error(*run(capsys, "intention", "train", "--target", "fly", "--out", str(tmp_path / "c"))[::2],
                      "unknown target behaviour")


@pytest.mark.slow
def test_attack_on_a_zoo_victim_then_attack_eval_from_the_cli(capsys, tmp_path):
    from rat.agents.sac import SACConfig
    from rat.experiments.presets import rat_config
    from rat.experiments.runner import attack_setup, train_attack
    from rat.preferences.reward_model import RewardModelConfig

    cfg = rat_config("cpu", budget=40, steps=900, adversary_hidden=32, adversary_every=100, adversary_batch=64,
                     refine_steps=0, weighting_every=300, eval_every=450, eval_episodes=1, final_eval_episodes=2, checkpoint_every=500,
                     pebble_overrides=dict(sac=SACConfig(hidden=32, layers=2, batch_size=32), seed_steps=100,
                                           unsupervised_steps=300, feedback_every=300,
                                           reward=RewardModelConfig(hidden=32, layers=2, max_epochs=3)))
    assert cfg.pebble.per_round == 20 and cfg.pebble.sac.batch_size == 32  # 2 rounds of 20 by 90% of the run
    report = train_attack("rat", attack_setup("zoo:drawer-open-v3", "reach", progress=False), cfg, tmp_path / "run")
    assert report.labels == 40 and report.details["adversary_updates"] > 0 and report.details["weighting_updates"] > 0
    assert report.max_perturbation <= 0.1 + 1e-9
    from PIL import Image

    assert Image.open(tmp_path / "run" / "training.png").text["Title"] == \
        "RAT reach against zoo:drawer-open-v3 attack success during training"

    code, out, err = run(capsys, "attack", "eval", str(tmp_path / "run"), "--episodes", "2", "--json")
    assert code == 0, err
    result = __import__("json").loads(out)
    assert result["within_budget"] and result["task"] == "drawer-open-v3" and result["target"] == "reach"
    assert result["clean_target_success_rate"] == 0.0  # the clean victim opens the drawer; it never reaches the goal
    assert result["refined_gap"] is None  # the network's Δ alone
    code, out, err = run(capsys, "attack", "eval", str(tmp_path / "run"), "--episodes", "1", "--refine-steps", "3",
                         "--refine-loss", "l2", "--json")  # Δ refined towards the saved π_θ at every observation
    refined = __import__("json").loads(out)
    assert code == 0 and refined["within_budget"] and 0.0 <= refined["refined_gap"] < 2 * 4 ** 0.5, err
    code, out, err = run(capsys, "attack", "eval", str(tmp_path / "run"), "--episodes", "1", "--refine-steps", "3",
                         "--refine-loss", "l2-or-q", "--refine-switch-gap", "1e9", "--json")  # no gap is above it
    assert code == 0 and __import__("json").loads(out)["refined_gap"] == refined["refined_gap"], err  # so l2's alone
    assert_user_error(*run(capsys, "attack", "eval", str(tmp_path / "run"), "--refine-steps", "3", "--refine-loss",
                           "q", "--refine-switch-gap", "0.5")[::2], "give --refine-loss l2-or-q with it")
    assert_user_error(*run(capsys, "attack", "eval", str(tmp_path / "run"), "--refine-steps", "3", "--refine-loss",
                           "l2-or-q", "--refine-switch-gap", "-1")[::2], "refine-switch-gap must be ≥ 0")
    code, out, err = run(capsys, "attack", "eval", str(tmp_path / "run" / "adversary.json"), "--episodes", "1",
                         "--refine-steps", "3")  # one saved adversary, named by its file
    assert code == 0 and "the gap left to its actions" in out, err

    from rat.experiments.runner import film_attack

    filmed = film_attack(tmp_path / "run", tmp_path / "attack.mp4", episodes=2, show=1)
    assert len(filmed) == 1 and (tmp_path / "attack.mp4").stat().st_size > 10_000


def test_attack_bad_inputs(capsys, tmp_path):
    assert_user_error(*run(capsys, "attack", "train", "--victim", "zoo:nope-v3", "--out", str(tmp_path / "a"))[::2],
                      "no zoo victim 'nope-v3'")
    assert_user_error(*run(capsys, "attack", "train", "--epsilon", "-0.1", "--out", str(tmp_path / "b"))[::2],
                      "epsilon must be a finite number >= 0")
    assert_user_error(*run(capsys, "attack", "train", "--budget", "-3", "--out", str(tmp_path / "c"))[::2],
                      "budget must not be negative")
    assert_user_error(*run(capsys, "attack", "eval", str(tmp_path))[::2], "no checkpoint at")
    # a zero label budget is an error for a run that learns from labels, before anything is written; an oracle
    # run needs no labels, and its configuration (built before the setup says oracle) takes the zero
    assert_user_error(*run(capsys, "attack", "train", "--budget", "0", "--out", str(tmp_path / "d"))[::2],
                      "the label budget is 0", "--reward oracle")
    assert not (tmp_path / "d").exists()
    from dataclasses import replace

    from rat.attacks.rat import RAT
    from rat.experiments.presets import rat_config
    from rat.experiments.runner import attack_setup
    oracle = RAT.configure(attack_setup("zoo:drawer-open-v3", "reach", reward="oracle", progress=False),
                           rat_config("cpu", budget=0))
    assert oracle.pebble.oracle and oracle.pebble.budget == 0
    oracle.pebble.check_budget("RAT")
    with pytest.raises(RatError, match="label budget is 0"):
        replace(oracle.pebble, oracle=False).check_budget("RAT")


@pytest.mark.slow
def test_zoo_regeneration_writes_victims_and_timings_and_refuses_weak_ones(capsys, tmp_path):
    dest = tmp_path / "zoo"
    code, out, err = run(capsys, "victim", "zoo", "--task", "drawer-close-v3", "--task", "window-close-v3", "--jobs", "1",
                         "--demo-episodes", "1", "--bc-updates", "20", "--eval-episodes", "2", "--dest", str(dest),
                         "--work-dir", str(tmp_path / "work"))
    for task in ("drawer-close-v3", "window-close-v3"):
        assert (dest / f"{task}.safetensors").exists() and (dest / f"{task}.json").exists()
        assert f"{task}" in out and "min" in out
    timings = __import__("json").loads((dest / "timings.json").read_text())
    assert set(timings) == {"drawer-close-v3", "window-close-v3"} and all(t["minutes"] > 0 for t in timings.values())
    # 20 updates of behaviour cloning make a poor victim: the command says so and exits 2
    weak = [t for t, r in timings.items() if r["clean_success"] < 0.95]
    if weak:
        assert_user_error(code, err, "below 95% clean success")
    else:
        assert code == 0


def test_a_victim_that_does_not_fit_leaves_no_run_behind(capsys, tmp_path):
    sb3 = pytest.importorskip("stable_baselines3")
    model = sb3.TD3("MlpPolicy", gym.make("Pendulum-v1"), learning_starts=10, policy_kwargs={"net_arch": [8]})
    model.save(tmp_path / "pendulum.zip")
    from point_env import BESIDE, PointGoal

    from rat.attacks import AttackSetup, ThreatModel
    from rat.attacks.rat import RATConfig, train_rat
    from rat.errors import RatError
    from rat.victims import load_victim

    with pytest.raises(RatError, match="does not fit"):
        train_rat(RATConfig(), AttackSetup(load_victim(str(tmp_path / "pendulum.zip")), BESIDE, PointGoal, ThreatModel()),
                  tmp_path / "run")
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_a_baseline_from_the_cli_then_attack_eval(capsys, tmp_path):
    code, out, err = run(capsys, "attack", "train", "--method", "random", "--target", "opposite", "--no-video",
                         "--set", "final_eval_episodes=4", "--out", str(tmp_path / "random"))
    assert code == 0 and "random (none) attack success" in out, err
    code, out, _ = run(capsys, "list", "attacks")
    assert code == 0 and all(name in out for name in ("rat", "random", "sa-rl", "pa-ad", "mad"))
    code, out, err = run(capsys, "attack", "eval", str(tmp_path / "random"), "--episodes", "2", "--json")
    result = __import__("json").loads(out)
    assert code == 0 and result["method"] == "random" and result["task"] == "drawer-close-v3" and result["within_budget"]
    assert_user_error(*run(capsys, "attack", "eval", str(tmp_path / "random"), "--refine-steps", "5")[::2],
                      "drop them")
    assert_user_error(*run(capsys, "attack", "eval", str(tmp_path / "random"), "--refine-loss", "q")[::2],
                      "drop them")
    assert_user_error(*run(capsys, "attack", "eval", str(tmp_path / "random"), "--refine-switch-gap", "1")[::2],
                      "drop them")


def test_baseline_and_grid_bad_inputs(capsys, tmp_path):
    assert_user_error(*run(capsys, "attack", "train", "--method", "sa-rl", "--labels", str(tmp_path / "none.sqlite"),
                           "--out", str(tmp_path / "a"))[::2], "no label store at")
    assert_user_error(*run(capsys, "attack", "train", "--method", "random", "--epsilon", "-1",
                           "--out", str(tmp_path / "b"))[::2], "epsilon must be a finite number >= 0")
    assert_user_error(*run(capsys, "attack", "train", "--method", "fgsm", "--out", str(tmp_path / "e"))[::2],
                      "unknown attack 'fgsm'", "rat list attacks")
    assert_user_error(*run(capsys, "bench", "table1", "--methods", "rat,fgsm", "--out", str(tmp_path / "c"))[::2],
                      "unknown method 'fgsm'")
    assert_user_error(*run(capsys, "bench", "table1", "--tasks", "drawer-opn-v3", "--out", str(tmp_path / "d"))[::2],
                      "did you mean 'drawer-open-v3'")
    assert not any((tmp_path / x).exists() for x in "abcde")


def test_settings_come_from_the_config_dataclasses():
    from rat.configs import field_default, field_doc, parse_assignment, with_values
    from rat.preferences.intention import IntentionConfig

    assert field_default(IntentionConfig, "pebble.sac.batch_size") == IntentionConfig().pebble.sac.batch_size
    assert field_doc(IntentionConfig, "pebble.budget") == "preference queries in all"
    assert parse_assignment(IntentionConfig, "pebble.teacher.beta=none") == ("pebble.teacher.beta", None)
    assert parse_assignment(IntentionConfig, "pebble.oracle=true") == ("pebble.oracle", True)
    config = with_values(IntentionConfig(), dict([parse_assignment(IntentionConfig, "pebble.budget=5_000")]))
    assert config.pebble.budget == 5000 and config.pebble.per_round == IntentionConfig().pebble.per_round
    with pytest.raises(RatError, match="'pebble.budgte' is not a setting of PebbleConfig"):
        parse_assignment(IntentionConfig, "pebble.budgte=1")
    with pytest.raises(RatError, match="expected int"):
        parse_assignment(IntentionConfig, "total_steps=many")


def test_every_config_option_shows_its_dataclass_default_and_bad_settings_are_one_line(capsys, tmp_path):
    from rat.cli import ConfigOption, cli

    def commands(group):
        for command in group.commands.values():
            yield from commands(command) if hasattr(command, "commands") else [command]

    options = [p for c in commands(cli) for p in c.params if isinstance(p, ConfigOption)]
    assert len(options) >= 25
    for option in options:
        record = option.get_help_record(click.Context(cli))
        assert option.help and (option.default is None or option.is_flag or f"[default: {option.default}" in record[1]), record
    assert_user_error(*run(capsys, "attack", "train", "--method", "random", "--set", "pgd_step=3",
                           "--out", str(tmp_path / "a"))[::2], "'pgd_step' is not a setting of SimpleConfig")
    assert_user_error(*run(capsys, "victim", "train", "--task", "drawer-open-v3", "--set", "bc_updates",
                           "--out", str(tmp_path / "b"))[::2], "is not name=value")
    assert not any((tmp_path / x).exists() for x in "ab")


def test_device_auto_picks_what_torch_sees_and_a_missing_gpu_is_one_line(capsys, tmp_path):
    import torch

    from rat.device import resolve_device

    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(RatError, match="unknown device 'tpu'"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        assert_user_error(*run(capsys, "attack", "train", "--method", "random", "--device", "cuda",
                               "--out", str(tmp_path / "r"))[::2], "does not apply to attack 'random'")
        assert_user_error(*run(capsys, "victim", "train", "--task", "drawer-close-v3", "--device", "cuda",
                               "--bc-updates", "1", "--demo-episodes", "1", "--out", str(tmp_path / "v"))[::2],
                          "torch sees no GPU")


@pytest.mark.parametrize("budget, steps, spend_by", [(1000, 50_000, 0.9), (9000, 50_000, 0.5), (3000, 100_000, 0.4),
                                                     (40, 3_000, 0.9)])
def test_the_cpu_preset_spends_exactly_the_label_budget_by_the_stated_step(budget, steps, spend_by):
    from rat.experiments.presets import rat_config

    config = rat_config("cpu" if steps > 3000 else "smoke", budget, steps, spend_by=spend_by)
    rounds = config.pebble.schedule.rounds()
    assert sum(n for _, n in rounds) == budget and config.pebble.budget == budget
    assert rounds[0][0] == config.pebble.warm_up  # the first round right after pre-training
    assert rounds[-1][0] <= max(config.pebble.warm_up, spend_by * steps)  # ... the last by the stated step


def test_the_eval_commands_refine_loss_choices_are_the_librarys():
    """The CLI keeps its imports light, so it lists the refinement losses itself; they must be the library's."""
    from rat.attacks.refine import REFINE_LOSSES
    from rat.cli import cli

    option = next(p for p in cli.commands["attack"].commands["eval"].params if p.name == "refine_loss")
    assert tuple(option.type.choices) == REFINE_LOSSES
