"""`rat audit` on the point environment: every cell measured, the page written with every section, a second call
measuring only what the first left, an audit killed mid-cell resumed, its page rendered in a real browser, the
budget respected, and bad requests refused in one line."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from point_env import BESIDE, OFFSET, PointGoal, point_victim
from test_rat_training import small_config

from rat.attacks import AttackSetup, ThreatModel
from rat.attacks.probe import ProbeConfig, register_steering
from rat.attacks.simple import SimpleConfig
from rat.errors import RatError
from rat.experiments.audit import check_audit, run_audit
from rat.pages import write_page

register_steering("beside", lambda obs: obs[2:] + OFFSET - obs[:2])


def setup_for(target, epsilon, reward):
    assert target == "beside"
    return AttackSetup(point_victim(), BESIDE, PointGoal, ThreatModel(epsilon), seed=0, reward=reward, progress=False)


def config_for(attack, target):
    return {"random": SimpleConfig(final_eval_episodes=20), "mad": SimpleConfig(final_eval_episodes=20),
            "probe": ProbeConfig(restarts=4, steps=10, final_eval_episodes=20), "rat": small_config(2000)}[attack]


@pytest.mark.slow
def test_an_audit_measures_every_cell_writes_its_page_and_resumes(tmp_path):
    first = run_audit(setup_for, config_for, ["beside"], [0.1, 0.05], tmp_path, 60, ["random", "probe"],
                      echo=lambda _: None, victim="go-to-goal")
    assert [(r["attack"], r["epsilon"], r["status"]) for r in first["rows"]] == [
        ("random", 0.05, "done"), ("random", 0.1, "done"), ("probe", 0.05, "done"), ("probe", 0.1, "done")]
    measured = {p: p.stat().st_mtime for p in tmp_path.glob("beside/*/*/report.json")}
    record = run_audit(setup_for, config_for, ["beside"], [0.05, 0.1], tmp_path, 60, ["random", "mad", "probe", "rat"],
                       echo=lambda _: None, victim="go-to-goal")
    assert {p: p.stat().st_mtime for p in measured} == measured  # the first call's cells are not run again
    rows = {(r["attack"], r["epsilon"]): r for r in record["rows"]}
    assert len(rows) == 8 and all(r["status"] == "done" for r in rows.values())
    probe, random = rows[("probe", 0.1)], rows[("random", 0.1)]
    assert probe["attack_success_rate"] >= 0.7 > random["attack_success_rate"]  # the probe steers; random does not
    assert probe["ci_low"] <= probe["attack_success_rate"] <= probe["ci_high"]
    assert all(r["max_perturbation"] <= r["epsilon"] + 1e-9 for r in rows.values())
    assert rows[("rat", 0.1)]["attacked_return"] is not None and rows[("rat", 0.1)]["clean_return"] < 0
    assert json.loads((tmp_path / "audit.json").read_text())["rows"] == record["rows"]
    page = write_page(tmp_path).read_text()
    for section in ("summary", "success-and-return-against", "table", "not-run"):
        assert f'id="{section}' in page, section
    assert 'src="audit.png"' in page and (tmp_path / "audit.png").stat().st_size > 10_000
    assert page.count("<tr><td>beside</td>") == 8


KILLABLE = """
import sys, torch
sys.path.insert(0, {tests!r})
torch.set_num_threads(1)
from test_audit import config_for, setup_for
from rat.experiments.audit import run_audit
run_audit(setup_for, config_for, ["beside"], [0.05, 0.1], {out!r}, 60, ["random", "rat"], echo=lambda _: None)
"""


def film_stand_in(run: Path, path: Path) -> None:
    """The point environment has no camera: a short clip of a moving square stands in for the filmed episodes."""
    from rat.eval import write_video

    frames = [np.zeros((64, 96, 3), np.uint8) for _ in range(20)]
    for i, frame in enumerate(frames):
        frame[20:40, 4 * i:4 * i + 20] = 255
    write_video(frames, path)


@pytest.fixture(scope="module")
def killed_audit(tmp_path_factory):
    """An audit killed while RAT trains its first cell (after a checkpoint), then called again to finish it."""
    out = tmp_path_factory.mktemp("audit")
    rat_cell = out / "beside" / "eps0.05" / "rat"
    proc = subprocess.Popen([sys.executable, "-c", KILLABLE.format(tests=str(Path(__file__).parent), out=str(out))])
    deadline = time.time() + 300
    while not (rat_cell / "checkpoint.json").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.01)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert (rat_cell / "checkpoint.json").exists() and not (rat_cell / "report.json").exists(), "not killed mid-cell"
    before = {p: p.stat().st_mtime for p in out.glob("beside/*/random/report.json")}
    record = run_audit(setup_for, config_for, ["beside"], [0.05, 0.1], out, 60, ["random", "rat"],
                       echo=lambda _: None, film=film_stand_in, victim="go-to-goal")
    return out, record, before


@pytest.mark.slow
def test_an_audit_killed_mid_cell_resumes_that_cell_and_keeps_the_finished_ones(killed_audit):
    out, record, before = killed_audit
    assert len(before) == 2 and {p: p.stat().st_mtime for p in before} == before  # measured once, kept
    assert [(r["attack"], r["epsilon"], r["status"]) for r in record["rows"]] == [
        ("random", 0.05, "done"), ("random", 0.1, "done"), ("rat", 0.05, "done"), ("rat", 0.1, "done")]
    from rat.reports import AttackReport

    resumed = AttackReport.read(out / "beside" / "eps0.05" / "rat")
    assert resumed.train_minutes > resumed.train_minutes_this_session  # it went on from the killed session's checkpoint
    videos = json.loads((out / "audit.json").read_text())["videos"]
    assert list(videos) == ["beside"] and videos["beside"].startswith("beside-eps0.1-") and (out / videos["beside"]).exists()


@pytest.mark.slow
def test_the_audit_page_renders_in_chromium_with_its_plot_and_video(killed_audit):
    from test_pages import CHROMIUM

    if CHROMIUM is None:
        pytest.skip("no Chromium: install it with `sudo apt-get install chromium` (make test does where it can)")
    playwright = pytest.importorskip("playwright.sync_api", reason="pip install playwright (the dev extra has it)")
    page_path = write_page(killed_audit[0])
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        page = browser.new_page()
        page.goto(page_path.as_uri())
        page.wait_for_load_state("load")
        for section in ("summary", "success-and-return-against", "table", "attacked-episodes", "not-run"):
            assert page.locator(f"section[id^='{section}'] h2").count() == 1, section
        assert page.locator("table tbody tr").count() == 4
        widths = page.eval_on_selector_all("img", "imgs => imgs.map(i => i.complete ? i.naturalWidth : 0)")
        assert widths and all(w > 100 for w in widths), widths  # audit.png found and decoded
        page.wait_for_function("document.querySelector('video').readyState >= 1 || document.querySelector('video').error")
        video = page.evaluate("(() => { const v = document.querySelector('video');"
                              " return [v.readyState, v.videoWidth, v.error && v.error.code]; })()")
        assert video[1] == 96 and video[2] is None, video  # the clip found and decoded
        browser.close()


def test_the_budget_is_checked_before_each_cell_and_what_did_not_run_is_said(tmp_path, monkeypatch):
    import rat.experiments.audit as audit

    clock = iter(np.arange(0, 10_000, 20.0))  # every reading of the clock: 20 seconds later
    monkeypatch.setattr(audit.time, "perf_counter", lambda: next(clock))
    record = run_audit(setup_for, config_for, ["beside"], [0.05, 0.1], tmp_path, 1, ["random", "mad"],
                       echo=lambda _: None)
    status = [(r["attack"], r["epsilon"], r["status"]) for r in record["rows"]]
    assert status[0] == ("random", 0.05, "done") and all(s == "not run" for *_, s in status[1:])
    assert "the budget of 1 minutes was spent" in record["rows"][-1]["why"]


@pytest.mark.parametrize("epsilons, minutes, attacks, message", [
    ([0.1, 0.0], 60, ["random"], "--epsilons must be budgets > 0"),
    ([-0.1], 60, ["random"], "--epsilons must be budgets > 0"),
    ([0.1], 0.2, ["random"], "a budget of 0.2 minutes runs no attack"),
    ([0.1], 60, ["fgsm"], "unknown attack 'fgsm'"),
])
def test_bad_audit_requests_are_named(epsilons, minutes, attacks, message):
    with pytest.raises(RatError, match=message):
        check_audit(epsilons, minutes, attacks)


def test_an_agent_that_does_not_fit_its_task_ends_in_one_line(tmp_path, capsys):
    from rat.cli import main

    assert main(["audit", "zoo:faucet-close-v3", "--task", "HalfCheetah-v5", "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "rat: error:" in err
    assert not (tmp_path / "a").exists()


def test_the_foreign_victims_table_pools_seeds_and_judges_rat_against_random_and_the_probe():
    from benchmark_scripts import load

    bench = load("foreign_attacks")

    def audit(rates, clean=0.0, n=30):
        return {"rows": [{"target": "reach", "epsilon": 0.1, "attack": a, "status": "done", "episodes": n,
                          "attack_success_rate": r, "clean_success_rate": clean} for a, r in rates.items()]
                + [{"target": "reach", "epsilon": 0.05, "attack": "rat", "status": "done", "episodes": n,
                    "attack_success_rate": 1.0, "clean_success_rate": clean}]}  # another ε: not pooled

    steered = [audit({"random": 0.0, "probe": 0.6, "rat": 0.5}), audit({"random": 0.1, "probe": 0.7, "rat": 0.4})]
    line = bench.summarise("v", {"algorithm": "sac"}, steered)
    assert line["seeds"] == 2 and line["rat_success"] == pytest.approx(27 / 60) and line["probe_steers"]
    assert line["rat_vs_random_p"] < 1e-4 and line["probe_minus_rat"] == pytest.approx(12 / 60)
    assert line["goal_met"] is True
    far = bench.summarise("v", {}, [audit({"random": 0.0, "probe": 0.9, "rat": 0.5})])
    assert far["goal_met"] is False  # 40 points below the probe
    unsteerable = bench.summarise("v", {}, [audit({"random": 0.0, "probe": 0.0, "rat": 0.0})])
    assert unsteerable["probe_steers"] is False and unsteerable["goal_met"] is None
    unfinished = bench.summarise("v", {}, [audit({"random": 0.0, "probe": 0.5})])
    assert unfinished["complete"] is False
    table = bench.table_markdown([line, far, unsteerable, unfinished])
    assert "| met |" in table and "**not met**" in table and "probe cannot steer" in table and "not finished" in table
