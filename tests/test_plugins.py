"""Plugins: a user's own attack and stateful target, registered outside the package, used from the CLI and a grid."""

import csv
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import rat.plugins
from rat.cli import main
from rat.envs import get_target

EXAMPLE = str(Path(__file__).resolve().parents[1] / "examples" / "my_attacks.py")


def run(capsys, *args):
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def test_a_stateful_target_counts_consecutive_steps_and_starts_afresh_each_episode():
    rat.plugins.load_plugin(EXAMPLE)
    target = get_target("hold-high")
    high, low = {"tcp_pos": [0, 0, 0.35]}, {"tcp_pos": [0, 0, 0.2]}
    first = target.episode_success()
    assert not any(first(high) for _ in range(19)) and first(high)  # the 20th step in a row succeeds
    second = target.episode_success()  # a new episode: its own count
    assert not second(high)
    assert not any(second(info) for info in [high] * 18 + [low] + [high] * 19)  # a dip restarts the count


@pytest.mark.slow
def test_a_plugin_attack_and_target_run_through_the_cli_and_a_one_cell_grid(capsys, tmp_path):
    code, out, err = run(capsys, "--plugin", EXAMPLE, "list", "attacks")
    assert code == 0 and "blind-hand" in out and "BlindHandConfig" in out, err
    code, out, _ = run(capsys, "--plugin", EXAMPLE, "list", "targets")
    assert code == 0 and "hold-high" in out

    code, out, err = run(capsys, "--plugin", EXAMPLE, "attack", "train", "--method", "blind-hand", "--target",
                         "hold-high", "--victim", "zoo:drawer-close-v3", "--set", "final_eval_episodes=2",
                         "--no-video", "--out", str(tmp_path / "attack"))
    assert code == 0 and "blind-hand (none) attack success" in out and "2 episodes" in out, err
    code, out, err = run(capsys, "--plugin", EXAMPLE, "attack", "eval", str(tmp_path / "attack"), "--episodes", "1")
    assert code == 0 and "blind-hand against zoo:drawer-close-v3" in out, err
    fresh = subprocess.run([sys.executable, "-m", "rat.cli", "attack", "eval", str(tmp_path / "attack")],
                           capture_output=True, text=True)  # a new process, without the plugin: one line
    assert fresh.returncode == 2 and "unknown attack 'blind-hand'" in fresh.stderr and "--plugin" in fresh.stderr

    grid = tmp_path / "grid"
    code, out, err = run(capsys, "--plugin", EXAMPLE, "bench", "table1", "--tasks", "drawer-close-v3", "--scenarios",
                         "hold-high", "--methods", "blind-hand", "--seeds", "0", "--preset", "smoke", "--jobs", "2",
                         "--out", str(grid))
    assert code == 0 and "ran 1" in out, err
    with open(grid / "results.csv") as f:
        (row,) = list(csv.DictReader(f))
    assert (row["scenario"], row["method"], row["episodes"]) == ("hold-high", "blind-hand", "2")
    assert "| hold-high | drawer-close-v3 |" in (grid / "table1.md").read_text()


def test_an_installed_plugin_loads_from_its_entry_point(tmp_path, monkeypatch):
    (tmp_path / "installed_targets.py").write_text(textwrap.dedent('''
        from rat.envs import register_target

        @register_target("installed-still", success=lambda info: False, description="from an entry point")
        def still(obs, action, next_obs, info):
            return 0.0
    '''))
    dist = tmp_path / "installed_targets-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: installed-targets\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[rat.plugins]\nstill = installed_targets\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(rat.plugins, "_installed_loaded", False)
    assert get_target("installed-still").description == "from an entry point"
    monkeypatch.delitem(sys.modules, "installed_targets")


def test_a_plugin_that_cannot_load_is_one_line(capsys, tmp_path):
    code, _, err = run(capsys, "--plugin", "no_such_module_here", "list", "attacks")
    assert code == 2 and err.count("\n") == 1 and "cannot be imported" in err and "PYTHONPATH" in err
    broken = tmp_path / "broken.py"
    broken.write_text("raise ValueError('half-written')\n")
    code, _, err = run(capsys, "--plugin", str(broken), "list", "attacks")
    assert code == 2 and err.count("\n") == 1 and "ValueError: half-written" in err
    code, _, err = run(capsys, "--plugin", str(tmp_path / "missing.py"), "list", "attacks")
    assert code == 2 and "does not exist" in err
