"""The table-1 grid runner: resumes without re-running finished cells, runs on a local Ray instance."""

import csv
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import torch

from rat.errors import RatError
from rat.experiments.presets import GRID_PRESETS
from rat.experiments.table1 import Cell, cell_progress, grid_cells, markdown_table, run_grid

SMOKE = GRID_PRESETS["smoke"]


def random_cells(seeds):
    return grid_cells(["drawer-open-v3"], ["manipulation"], ["random"], seeds)


@pytest.mark.slow
def test_a_grid_resumes_without_rerunning_finished_cells(tmp_path):
    said = []
    first = run_grid(random_cells([0, 1]), SMOKE, tmp_path, jobs=2, echo=said.append, heartbeat=0.2)
    assert len(first["ran"]) == 2 and not first["failed"]
    assert any(line.startswith("running:") for line in said)  # a quiet grid still says it is alive
    assert sum("min of training over every session" in line for line in said) == 2  # a resumed cell's time in all
    stamps = {c.key: (c.directory(tmp_path) / "result.json").stat().st_mtime_ns for c in random_cells([0, 1])}
    second = run_grid(random_cells([0, 1, 2]), SMOKE, tmp_path, jobs=1, echo=lambda _: None)
    assert sorted(second["skipped"]) == sorted(stamps) and [r["seed"] for r in second["ran"]] == [2]
    assert {c.key: (c.directory(tmp_path) / "result.json").stat().st_mtime_ns for c in random_cells([0, 1])} == stamps
    with open(tmp_path / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["seed"]) for r in rows] == [0, 1, 2] and all(r["preset"] == "smoke" for r in rows)
    run_grid(random_cells([2]), SMOKE, tmp_path, echo=lambda _: None)  # a call for one cell keeps the others' rows
    with open(tmp_path / "results.csv") as f:
        assert [int(r["seed"]) for r in csv.DictReader(f)] == [0, 1, 2]
    assert all(r["victim"] == "zoo:drawer-open-v3" and r["victim_method"].startswith("sac") for r in rows)
    assert all(0 <= float(r["clean_success_rate"]) <= 1 for r in rows)  # the unattacked victim, the yardstick
    assert all(r["refined_gap"] == "" for r in rows)  # the column is there; only a refined RAT cell fills it
    assert json.loads((tmp_path / "grid.json").read_text())["preset"]["name"] == "smoke"
    table = (tmp_path / "table1.md").read_text()
    assert "| manipulation | drawer-open-v3 |" in table and "/ 97.5" in table and "| clean |" in table  # the paper's RAT figure beside ours
    with pytest.raises(RatError, match="other budgets"):
        run_grid(random_cells([0]), GRID_PRESETS["cpu"], tmp_path, echo=lambda _: None)


def test_a_preference_baseline_waits_for_its_rat_cells_labels(tmp_path):
    result = run_grid(grid_cells(["drawer-open-v3"], ["manipulation"], ["sa-rl"], [0]), SMOKE, tmp_path, jobs=1,
                      echo=lambda _: None)
    assert len(result["failed"]) == 1 and "needs the labels of drawer-open-v3/manipulation/rat/seed0" in result["failed"][0]["error"]
    assert (Cell("drawer-open-v3", "manipulation", "sa-rl", 0).directory(tmp_path) / "error.txt").exists()


def test_a_running_cell_reports_the_step_its_run_has_logged(tmp_path):
    cell = Cell("drawer-open-v3", "opposite", "rat", 0)
    run = cell.directory(tmp_path) / "run"
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"rat": {"total_steps": 50000}}))
    (run / "metrics.csv").write_text("step,behaviour_success\n500,0.0\n12000,1.0\n")
    assert cell_progress(cell, tmp_path, within=60) == "drawer-open-v3/opposite/rat/seed0 step 12000/50000"
    (run / "config.json").write_text('{"rat": {"tot')  # damaged: the cell's own run refuses it; the line goes on
    assert cell_progress(cell, tmp_path, within=60) == "drawer-open-v3/opposite/rat/seed0 step 12000/?"
    old = time.time() - 120
    os.utime(run / "metrics.csv", (old, old))
    assert cell_progress(cell, tmp_path, within=60) is None  # not logged lately: waiting or stopped
    (run.parent / "result.json").write_text("{}")
    assert cell_progress(cell, tmp_path, within=1e9) is None  # finished


def test_bad_grids_are_refused_in_one_line():
    with pytest.raises(RatError, match="unknown method 'fgsm'"):
        grid_cells(["drawer-open-v3"], ["manipulation"], ["fgsm"], [0])
    with pytest.raises(RatError, match="unknown scenario"):
        grid_cells(["drawer-open-v3"], ["sideways"], ["rat"], [0])
    with pytest.raises(RatError, match="unknown task"):
        grid_cells(["drawer-opn-v3"], ["manipulation"], ["rat"], [0])


def test_the_markdown_table_puts_the_papers_opposite_row_beside_ours():
    rows = [{"task": "faucet-close-v3", "scenario": "opposite", "method": "rat", "seed": s,
             "attack_success_rate": v} for s, v in enumerate((0.5, 1.0))]
    table = markdown_table(rows, SMOKE)
    assert "| opposite | faucet-close-v3 (faucet-open-v3) |" in table and "**75.0 ± 25.0** (2) / 81.5" in table


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_a_two_cell_grid_runs_on_a_local_ray_instance(tmp_path):
    ray = pytest.importorskip("ray")
    ray_bin = Path(sys.executable).parent / "ray"
    port, temp = _free_port(), tempfile.mkdtemp(prefix="ray-")  # short: Ray's socket paths must fit 107 bytes
    start = [str(ray_bin), "start", "--head", f"--port={port}", "--num-cpus=2", "--include-dashboard=false",
             "--disable-usage-stats", f"--temp-dir={temp}"]
    subprocess.run(start, check=True, capture_output=True, timeout=180)
    try:
        result = run_grid(random_cells([0, 1]), SMOKE, tmp_path / "grid", ray_address=f"127.0.0.1:{port}",
                          echo=lambda _: None)
        assert len(result["ran"]) == 2 and not result["failed"]
        assert all((c.directory(tmp_path / "grid") / "result.json").exists() for c in random_cells([0, 1]))
    finally:
        ray.shutdown()
        subprocess.run([str(ray_bin), "stop", "--force"], capture_output=True, timeout=120)
        shutil.rmtree(temp, ignore_errors=True)


def test_the_cpu_grid_asks_the_papers_label_counts_per_row_unless_told_otherwise():
    cpu = GRID_PRESETS["cpu"]
    counts = {(task, scenario): cpu.labels_for(Cell(task, scenario, "rat", 0))
              for task in ("drawer-open-v3", "faucet-close-v3", "window-close-v3")
              for scenario in ("manipulation", "opposite")}
    assert counts == {("drawer-open-v3", "manipulation"): 9000, ("drawer-open-v3", "opposite"): 3000,  # drawer-close
                      ("faucet-close-v3", "manipulation"): 9000, ("faucet-close-v3", "opposite"): 5000,  # faucet-open
                      ("window-close-v3", "manipulation"): 9000, ("window-close-v3", "opposite"): 5000}  # window-open
    assert cpu.labels_for(Cell("dt/halfcheetah-v5", "cheetah-backward", "rat", 0)) == 3000  # a named target
    old = cpu.with_labels({"manipulation": 3000, "opposite": 1000})  # the first grid of docs/notes/table1-log.md
    assert old.labels_for(Cell("faucet-close-v3", "opposite", "rat", 0)) == 1000
    assert old.labels_for(Cell("drawer-open-v3", "manipulation", "rat", 0)) == 3000
    with pytest.raises(RatError, match="give manipulation=N, opposite=N or target=N"):
        cpu.with_labels({"sideways": 10})


def test_the_grid_command_takes_label_counts_in_one_line(tmp_path, capsys):
    from rat.cli import main

    assert main(["bench", "table1", "--labels", "manipulation:3000", "--out", str(tmp_path / "g")]) != 0
    assert "--labels 'manipulation:3000' is not SCENARIO=N" in capsys.readouterr().err
    assert not (tmp_path / "g").exists()


def test_the_reports_of_a_grid_stopped_part_way_come_from_its_finished_cells(tmp_path, capsys):
    from dataclasses import asdict

    from rat.cli import main

    cells = random_cells([0, 1, 2])
    (tmp_path / "grid.json").write_text(json.dumps({"preset": asdict(SMOKE), "cells": [c.key for c in cells]}))
    for cell, success in zip(cells[:2], (0.25, 0.75)):  # seeds 0 and 1 finished, seed 2 never ran
        cell.directory(tmp_path).mkdir(parents=True)
        (cell.directory(tmp_path) / "result.json").write_text(json.dumps(
            {**asdict(cell), "attack_success_rate": success, "clean_success_rate": 0.0, "victim": "zoo:drawer-open-v3"}))
    assert main(["bench", "table1", "--report-only", "--out", str(tmp_path)]) == 0
    assert "2 of the grid's 3 cells finished" in capsys.readouterr().out
    with open(tmp_path / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert [(r["seed"], r["attack_success_rate"], r["victim"]) for r in rows] == [
        ("0", "0.25", "zoo:drawer-open-v3"), ("1", "0.75", "zoo:drawer-open-v3")]
    assert "**50.0 ± 25.0** (2)" in (tmp_path / "table1.md").read_text()  # the two seeds' mean ± std
    assert not cells[2].directory(tmp_path).exists()  # nothing ran

    assert main(["bench", "table1", "--report-only", "--out", str(tmp_path / "nothing")]) != 0
    assert "holds no grid (no grid.json)" in capsys.readouterr().err
    (tmp_path / "grid.json").write_text("{not json")
    assert main(["bench", "table1", "--report-only", "--out", str(tmp_path)]) != 0
    assert "is not a grid record" in capsys.readouterr().err
    with pytest.raises(RatError, match="is not a grid record"):  # a grid run into it refuses too, before any cell
        run_grid(random_cells([2]), SMOKE, tmp_path, jobs=1, echo=lambda _: None)
    assert (tmp_path / "grid.json").read_text() == "{not json" and not cells[2].directory(tmp_path).exists()


@pytest.mark.slow
def test_a_finished_rat_run_is_taken_in_as_its_cell_and_keeps_its_numbers(tmp_path, monkeypatch):
    from dataclasses import replace

    from rat.attacks import ThreatModel
    from rat.experiments.runner import attack_setup, train_attack
    from rat.experiments.table1 import cell_config

    preset = replace(SMOKE, rat_steps=1500, baseline_reward="rat")
    cell = Cell("drawer-open-v3", "manipulation", "rat", 0)
    setup = attack_setup("zoo:drawer-open-v3", "reach", ThreatModel(preset.epsilon, preset.norm), 0, progress=False)
    alone = tmp_path / "alone"  # `rat attack train` with the cell's settings, checkpointing more often
    report = train_attack("rat", setup, replace(cell_config(cell, preset), checkpoint_every=500), alone)
    trained = (alone / "metrics.csv").read_text()

    grid = tmp_path / "grid"
    with pytest.raises(RatError, match=r"is no RAT cell of this grid"):  # seed 0's run, a grid of seed 1
        run_grid([Cell("drawer-open-v3", "manipulation", "rat", 1)], preset, grid, echo=lambda _: None, adopt=[alone])
    with pytest.raises(RatError, match=r"differs in: rat\.total_steps = 1500 in the run, 2000 now"):
        run_grid([cell], replace(preset, rat_steps=2000), tmp_path / "other", echo=lambda _: None, adopt=[alone])
    assert not cell.directory(grid).exists() and not cell.directory(tmp_path / "other").exists()  # nothing copied

    said = []
    sa_rl = Cell("drawer-open-v3", "manipulation", "sa-rl", 0)  # attacks with the r̂ the RAT cell ended with
    monkeypatch.chdir(tmp_path)  # the run named as a user names it; the table keeps that name, not this machine's path
    named = Path("alone")
    result = run_grid([cell, sa_rl], preset, grid, jobs=1, echo=said.append, adopt=[named])
    assert f"{cell.key}: adopted '{named}'" in said
    row, baseline = result["ran"]
    assert row["adopted_from"] == "alone"
    assert row["attack_success_rate"] == report.attack_success_rate and row["labels"] == report.labels
    assert (cell.directory(grid) / "run" / "metrics.csv").read_text() == trained  # evaluated, not trained again
    with open(grid / "results.csv") as f:
        assert {r["method"]: r["adopted_from"] for r in csv.DictReader(f)} == {"rat": "alone", "sa-rl": ""}
    again = run_grid([cell, sa_rl], preset, grid, jobs=1, echo=lambda _: None, adopt=[alone])  # the same run, named anew
    assert sorted(again["skipped"]) == sorted([cell.key, sa_rl.key]) and not again["ran"]
    run = cell.directory(grid) / "run"
    assert baseline["method"] == "sa-rl" and baseline["labels"] == report.labels
    assert json.loads((sa_rl.directory(grid) / "result.json").read_text())["labels"] == report.labels
    assert json.loads((sa_rl.directory(grid) / "run" / "report.json").read_text())["details"]["reward_from_run"] == str(run)
    assert not list(run.glob("labels-reward-seed*"))  # nothing learnt offline

    from rat.checkpoint import load_checkpoint
    from rat.preferences.offline import run_reward

    ensemble, info = run_reward(run, 39, 4)
    ended = load_checkpoint(run / "checkpoint")[0]["learner"]["ensemble"]
    assert all(torch.equal(v, ended[k]) for k, v in ensemble.state_dict().items()) and len(info["label_ids"]) == 40
    with pytest.raises(RatError, match="does not fit observations 12-d"):
        run_reward(run, 12, 4)


def test_a_baseline_given_a_run_that_has_not_finished_or_learnt_no_reward_is_refused(tmp_path):
    from rat.preferences.offline import run_reward

    (tmp_path / "config.json").write_text(json.dumps({"rat": {"pebble": {"oracle": True, "reward": {}}}}))
    with pytest.raises(RatError, match="is not a finished RAT run"):
        run_reward(tmp_path, 39, 4)
    (tmp_path / "report.json").write_text("{}")
    (tmp_path / "checkpoint.json").write_text("{}")
    with pytest.raises(RatError, match="learnt no r̂ \\(it is an oracle run\\)"):
        run_reward(tmp_path, 39, 4)
    (tmp_path / "config.json").write_text('{"rat": ')
    with pytest.raises(RatError, match="config.json' is corrupted \\(JSONDecodeError\\)"):
        run_reward(tmp_path, 39, 4)
    from dataclasses import replace

    with pytest.raises(RatError, match="baseline reward 'mine': use one of offline, rat"):
        replace(SMOKE, baseline_reward="mine")


def test_the_curves_mark_each_methods_deployed_attack_beside_its_training_evaluations(tmp_path, monkeypatch):
    """A refined RAT cell's evaluations during training (the network's Δ) can read 0% where the table says 90%."""
    import rat.plots
    from rat.experiments.table1 import plot_curves

    real = rat.plots.pyplot()
    figures = []
    monkeypatch.setattr(real, "close", figures.append)  # keep the figure to read its lines
    monkeypatch.setattr(rat.plots, "pyplot", lambda: real)
    rows = []
    for seed, final in ((0, 0.8), (1, 1.0)):
        run = Cell("drawer-open-v3", "manipulation", "rat", seed).directory(tmp_path) / "run"
        run.mkdir(parents=True)
        (run / "metrics.csv").write_text("step,eval_success_rate\n10,\n1000,0.0\n2000,0.0\n")
        rows.append({"task": "drawer-open-v3", "scenario": "manipulation", "method": "rat", "seed": seed,
                     "attack_success_rate": final})
    plot_curves(tmp_path, "drawer-open-v3", rows)
    lines = figures[0].axes[0].get_lines()
    curve = [line for line in lines if line.get_marker() == "o"]
    stars = [line for line in lines if line.get_marker() == "*" and len(line.get_xdata())]
    assert list(curve[0].get_ydata()) == [0.0, 0.0]
    assert [(list(s.get_xdata()), list(s.get_ydata())) for s in stars] == [([2000], [90.0])]


def test_bench_report_regenerates_the_committed_table_byte_for_byte(tmp_path, capsys):
    import shutil
    from pathlib import Path

    from rat.cli import main

    committed = Path(__file__).resolve().parent.parent / "benchmarks" / "table1"
    shutil.copy(committed / "results.csv", tmp_path / "results.csv")
    assert main(["bench", "report", str(tmp_path)]) == 0
    assert (tmp_path / "table1.md").read_bytes() == (committed / "table1.md").read_bytes()
    page = (committed / "table1.md").read_text()
    assert "| SAC |" in page and "| behaviour clone |" in page  # both kinds of victim, side by side
    assert main(["bench", "report", str(tmp_path / "empty")]) == 2
    assert "holds no results.csv" in capsys.readouterr().err
