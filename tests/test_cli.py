"""The CLI, called in-process. Bad input: exit code 2 and one line on stderr naming the fix."""

import sys

import gymnasium as gym
import pytest

from rat.cli import main
from rat.checkpoint import save_checkpoint


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
    assert_user_error(*run(capsys, "victim", "train", "--task", "drawer-open-v3", "--bc-updates", "-1",
                           "--out", str(tmp_path / "r"))[::2], "bc-updates must be positive")
