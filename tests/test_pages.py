"""`rat report`: one static page of a run or a grid, checked as text and in a real browser."""

import json
import shutil
from pathlib import Path

import pytest

from rat.cli import main
from rat.pages import markdown_to_html

ROOT = Path(__file__).resolve().parent.parent
RUN = ROOT / "benchmarks" / "strength-runs" / "draweropen-reach9k-100k-seed0"  # a finished RAT run, kept in git
GRID = ROOT / "benchmarks" / "table1"
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture
def pages(tmp_path):
    """Copies of a run and of the table-1 grid, each with its page written by `rat report`."""
    run, grid = tmp_path / "run", tmp_path / "grid"
    shutil.copytree(RUN, run)
    grid.mkdir()
    for name in ("results.csv", "table1.md", "attack-drawer-open-opposite-seed0.png"):
        shutil.copy(GRID / name, grid / name)
    for folder in (run, grid):
        assert main(["report", str(folder)]) == 0
    return run / "report.html", grid / "report.html"


def test_the_pages_hold_the_runs_summary_plot_and_settings_and_the_grids_table(pages):
    run, grid = (p.read_text() for p in pages)
    report = json.loads((RUN / "report.json").read_text())
    assert 'id="summary"' in run and 'id="training"' in run and 'id="settings"' in run
    assert f"{100 * report['attack_success_rate']:.1f}%" in run and 'src="training.png"' in run
    rows = [line for line in (GRID / "table1.md").read_text().splitlines() if line.startswith("| ")]
    assert grid.count("<tr>") == len(rows) - 1  # every row of the table (the header's own), none of the rule
    assert "<strong>" in grid and 'src="attack-drawer-open-opposite-seed0.png"' in grid


def test_markdown_tables_escape_what_they_hold():
    out = markdown_to_html("| a | b |\n| --- | ---: |\n| <script> | **1.0** |")
    assert "&lt;script&gt;" in out and "<script>" not in out and "<td class=num><strong>1.0</strong></td>" in out


def test_a_folder_that_is_neither_run_nor_grid_is_named(tmp_path, capsys):
    assert main(["report", str(tmp_path)]) == 2
    assert "neither a finished run" in capsys.readouterr().err


@pytest.mark.slow
def test_the_pages_render_in_chromium_with_their_images_loaded(pages):
    if CHROMIUM is None:
        pytest.skip("no Chromium: install it with `sudo apt-get install chromium` (make test does where it can)")
    playwright = pytest.importorskip("playwright.sync_api", reason="pip install playwright (the dev extra has it)")
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        page = browser.new_page()
        for path, sections in zip(pages, (["summary", "training", "settings"], ["table", "curves"])):
            page.goto(path.as_uri())
            page.wait_for_load_state("load")
            assert [page.locator(f"section#{s} h2").count() for s in sections] == [1] * len(sections)
            widths = page.eval_on_selector_all("img", "imgs => imgs.map(i => i.complete ? i.naturalWidth : 0)")
            assert widths and all(w > 100 for w in widths), widths  # every image found and decoded
        table_rows = [line for line in (GRID / "table1.md").read_text().splitlines() if line.startswith("| ")]
        assert page.locator("table tbody tr").count() == len(table_rows) - 2  # the grid's table, rendered
        browser.close()
