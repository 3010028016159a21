"""The paper's table 1 on one command: a resumable grid of task × scenario × method × seed.

Every cell trains one attack against the zoo victim of its task and evaluates it over 30
episodes; its directory is ``<out>/cells/<task>/<scenario>/<method>/seed<k>/``, and the cell is
finished when its ``result.json`` exists (written last, atomically), so re-running a grid skips
finished cells and resumes interrupted ones from their checkpoints.

Methods are the paper's columns: ``pa-ad-oracle``, ``pa-ad``, ``sa-rl-oracle``, ``sa-rl``,
``random``, ``rat``. The preference-based ``sa-rl`` and ``pa-ad`` learn r̂ from the label store
of the ``rat`` cell with the same task, scenario and seed, so they run after it.

Cells run in parallel local processes, or as Ray tasks on a cluster given its address
(``pip install 'rat[ray]'``). Budgets come from a :class:`GridPreset` and are recorded in
``grid.json`` beside the results: ``results.csv`` (every number), ``table1.md`` (laid out like
the paper's table 1, the paper's figure beside ours) and ``curves-<task>.png``.
"""

from __future__ import annotations

import csv
import json
import os
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass, field, replace
from multiprocessing import get_context
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from rat.errors import RatError, require

METHODS = ("pa-ad-oracle", "pa-ad", "sa-rl-oracle", "sa-rl", "random", "rat")  # the paper's column order
METHOD_NAMES = {"pa-ad-oracle": "PA-AD (oracle)", "pa-ad": "PA-AD", "sa-rl-oracle": "SA-RL (oracle)",
                "sa-rl": "SA-RL", "random": "Random", "rat": "RAT"}
SCENARIOS = {"manipulation": "reach", "opposite": "opposite"}  # scenario -> target behaviour
NEEDS_LABELS = ("sa-rl", "pa-ad")

#: The paper's table 1 (mean, std over seeds, %), keyed by (scenario, row task). Rows of the
#: manipulation scenario are the victim's task; rows of the opposite scenario are the behaviour
#: the attacker wants, i.e. the environment the opposite victim is attacked in.
PAPER_TABLE1: dict[tuple[str, str], dict[str, tuple[float, float]]] = {
    ("manipulation", "door-lock-v3"): {"pa-ad-oracle": (4.5, 4.0), "pa-ad": (3.5, 6.63), "sa-rl-oracle": (76.5, 14.97), "sa-rl": (39.5, 30.48), "random": (0.0, 0.0), "rat": (87.0, 10.0)},
    ("manipulation", "door-unlock-v3"): {"pa-ad-oracle": (0.0, 0.0), "pa-ad": (0.0, 0.0), "sa-rl-oracle": (11.11, 13.43), "sa-rl": (0.56, 0.0), "random": (0.0, 0.0), "rat": (97.0, 6.63)},
    ("manipulation", "window-open-v3"): {"pa-ad-oracle": (0.0, 0.0), "pa-ad": (0.0, 0.0), "sa-rl-oracle": (30.0, 21.19), "sa-rl": (8.0, 15.13), "random": (0.0, 0.0), "rat": (72.5, 19.62)},
    ("manipulation", "window-close-v3"): {"pa-ad-oracle": (0.0, 0.0), "pa-ad": (0.5, 0.0), "sa-rl-oracle": (99.0, 3.0), "sa-rl": (23.5, 37.22), "random": (0.0, 0.0), "rat": (72.5, 40.01)},
    ("manipulation", "drawer-open-v3"): {"pa-ad-oracle": (0.0, 0.0), "pa-ad": (0.0, 0.0), "sa-rl-oracle": (100.0, 0.0), "sa-rl": (26.0, 27.28), "random": (0.0, 0.0), "rat": (97.5, 4.0)},
    ("manipulation", "drawer-close-v3"): {"pa-ad-oracle": (0.0, 0.0), "pa-ad": (0.0, 0.0), "sa-rl-oracle": (57.5, 18.0), "sa-rl": (4.0, 8.0), "random": (0.0, 0.0), "rat": (76.0, 24.98)},
    ("manipulation", "faucet-open-v3"): {"pa-ad-oracle": (1.5, 4.0), "pa-ad": (2.5, 4.0), "sa-rl-oracle": (63.5, 20.52), "sa-rl": (0.0, 0.0), "random": (0.0, 0.0), "rat": (84.0, 21.19)},
    ("manipulation", "faucet-close-v3"): {"pa-ad-oracle": (0.0, 0.0), "pa-ad": (0.0, 0.0), "sa-rl-oracle": (66.5, 16.85), "sa-rl": (4.5, 9.22), "random": (0.0, 0.0), "rat": (91.0, 6.71)},
    ("opposite", "door-lock-v3"): {"pa-ad-oracle": (9.5, 7.48), "pa-ad": (10.0, 9.17), "sa-rl-oracle": (8.0, 13.42), "sa-rl": (2.0, 0.0), "random": (1.0, 3.0), "rat": (99.0, 3.0)},
    ("opposite", "door-unlock-v3"): {"pa-ad-oracle": (3.0, 5.0), "pa-ad": (4.0, 4.58), "sa-rl-oracle": (8.0, 18.33), "sa-rl": (6.0, 12.0), "random": (0.0, 0.0), "rat": (98.5, 4.0)},
    ("opposite", "window-open-v3"): {"pa-ad-oracle": (15.5, 12.21), "pa-ad": (17.0, 11.14), "sa-rl-oracle": (15.0, 16.61), "sa-rl": (7.0, 16.12), "random": (1.0, 3.0), "rat": (77.5, 33.41)},
    ("opposite", "window-close-v3"): {"pa-ad-oracle": (38.5, 23.69), "pa-ad": (55.0, 14.7), "sa-rl-oracle": (63.0, 34.7), "sa-rl": (20.0, 39.8), "random": (5.5, 5.0), "rat": (99.0, 0.0)},
    ("opposite", "drawer-open-v3"): {"pa-ad-oracle": (1.5, 4.0), "pa-ad": (0.5, 3.0), "sa-rl-oracle": (1.11, 0.0), "sa-rl": (3.0, 0.0), "random": (0.0, 0.0), "rat": (85.5, 29.34)},
    ("opposite", "drawer-close-v3"): {"pa-ad-oracle": (88.5, 7.81), "pa-ad": (79.0, 18.44), "sa-rl-oracle": (81.0, 20.88), "sa-rl": (63.0, 32.5), "random": (0.0, 0.0), "rat": (92.0, 17.32)},
    ("opposite", "faucet-open-v3"): {"pa-ad-oracle": (6.5, 9.0), "pa-ad": (10.0, 13.75), "sa-rl-oracle": (6.0, 18.0), "sa-rl": (0.0, 0.0), "random": (0.0, 0.0), "rat": (81.5, 29.68)},
    ("opposite", "faucet-close-v3"): {"pa-ad-oracle": (19.0, 13.27), "pa-ad": (32.0, 11.0), "sa-rl-oracle": (7.0, 12.81), "sa-rl": (8.0, 16.0), "random": (0.5, 0.0), "rat": (96.0, 12.81)},
}


@dataclass(frozen=True)
class GridPreset:
    """Budgets of every cell of a grid (recorded in ``grid.json``)."""

    name: str
    rat_preset: str  #: :func:`rat.attacks.presets.rat_config` preset
    rat_steps: int  #: RAT environment steps
    labels: dict[str, int]  #: preference labels per scenario (RAT's, and so the preference baselines')
    ppo_preset: str  #: :func:`rat.attacks.baselines.ppo_preset` preset
    ppo_steps: int  #: SA-RL / PA-AD environment steps
    episodes: int = 30  #: final evaluation episodes per cell (the paper's 30)
    epsilon: float = 0.1
    norm: str = "linf"
    labels_by_row: dict = field(default_factory=dict)  #: per paper row "scenario/task", overriding ``labels``
    overrides: dict = field(default_factory=dict)  #: other RATConfig fields (small runs)
    pebble_overrides: dict = field(default_factory=dict)  #: other PebbleConfig fields (small runs)


    def labels_for(self, cell: "Cell") -> int:
        row = f"{cell.scenario}/{paper_row(cell.task, cell.scenario)}"
        return int(self.labels_by_row.get(row, self.labels[cell.scenario]))


#: The paper's label budgets (section 5.1): 9,000 in the manipulation scenario; per task in the opposite one.
PAPER_OPPOSITE_LABELS = {"window-close-v3": 1000, "drawer-close-v3": 3000, "faucet-open-v3": 5000,
                         "faucet-close-v3": 5000, "window-open-v3": 5000, "drawer-open-v3": 7000,
                         "door-lock-v3": 7000, "door-unlock-v3": 7000}

GRID_PRESETS = {
    # The paper's budgets (a GPU cluster): 10⁶ steps for every learner, its label counts.
    "paper": GridPreset("paper", "paper", 1_000_000, {"manipulation": 9000, "opposite": 5000}, "paper", 1_000_000,
                        labels_by_row={f"opposite/{t}": n for t, n in PAPER_OPPOSITE_LABELS.items()}),
    # This project's 2-core CPU machine: 5×10⁴ steps per learner.
    "cpu": GridPreset("cpu", "cpu", 50_000, {"manipulation": 3000, "opposite": 1000}, "cpu", 50_000),
    # Minutes, not results: for trying a grid or a cluster end to end.
    "smoke": GridPreset("smoke", "cpu", 3_000, {"manipulation": 40, "opposite": 40}, "cpu", 2_048, episodes=2,
                        overrides={"eval_every": 1_000, "eval_episodes": 1},
                        pebble_overrides={"seed_steps": 500, "unsupervised_steps": 500, "feedback_every": 1_000}),
}


@dataclass(frozen=True)
class Cell:
    task: str  #: the victim's task (zoo:<task>)
    scenario: str  #: manipulation or opposite
    method: str
    seed: int

    @property
    def key(self) -> str:
        return f"{self.task}/{self.scenario}/{self.method}/seed{self.seed}"

    def directory(self, out: Path) -> Path:
        return Path(out) / "cells" / self.key

    def label_source(self) -> "Cell":
        """The RAT cell whose labels a preference-based baseline learns from."""
        return Cell(self.task, self.scenario, "rat", self.seed)


def grid_cells(tasks: Iterable[str], scenarios: Iterable[str], methods: Iterable[str], seeds: Iterable[int]) -> list[Cell]:
    from rat.envs import check_task

    tasks, scenarios, methods, seeds = list(tasks), list(scenarios), list(methods), list(seeds)
    for task in tasks:
        check_task(task)
    for name, given, known in (("scenario", scenarios, SCENARIOS), ("method", methods, METHODS)):
        unknown = [g for g in given if g not in known]
        if unknown:
            raise RatError(f"unknown {name} '{unknown[0]}'; use some of: {', '.join(known)}")
    if any(s < 0 for s in seeds) or not (tasks and scenarios and methods and seeds):
        raise RatError("a grid needs at least one task, scenario, method and seed (seeds >= 0)")
    return [Cell(t, s, m, k) for t in tasks for s in scenarios for m in methods for k in seeds]


def run_cell(cell: Cell, preset: GridPreset, out: str | Path) -> dict:
    """Train and evaluate one cell (resuming it if interrupted); returns its result row."""
    import torch

    from rat.attacks.baselines import ppo_preset
    from rat.attacks.presets import rat_config, train_attack, train_baseline_attack

    torch.set_num_threads(1)  # one core per cell; cells run side by side
    directory = cell.directory(Path(out))
    victim, target = f"zoo:{cell.task}", SCENARIOS[cell.scenario]
    started = time.perf_counter()
    if cell.method == "rat":
        config = rat_config(preset.rat_preset, preset.labels_for(cell), preset.rat_steps, target,
                            epsilon=preset.epsilon, norm=preset.norm, seed=cell.seed,
                            final_eval_episodes=preset.episodes, **preset.overrides)
        config = replace(config, pebble=replace(config.pebble, **preset.pebble_overrides))
        report = train_attack(victim, target, config, directory / "run", progress=False)
    else:
        method = cell.method.removesuffix("-oracle")
        labels = None
        if cell.method in NEEDS_LABELS:
            labels = cell.label_source().directory(Path(out)) / "run" / "labels.sqlite"
            if finished(cell.label_source(), Path(out)) is None:
                raise RatError(f"cell {cell.key} needs the labels of {cell.label_source().key}, which has not run")
        ppo = ppo_preset(preset.ppo_preset, preset.ppo_steps, final_eval_episodes=preset.episodes)
        report = train_baseline_attack(method, victim, target, directory / "run", preset.epsilon, preset.norm,
                                       cell.seed, ppo, labels, progress=False)
    row = {**asdict(cell), "attack_success_rate": report["attack_success_rate"],
           "ci_low": report["attack_success_ci"][0], "ci_high": report["attack_success_ci"][1],
           "episodes": report["episodes"], "labels": report.get("labels") or 0,
           "max_perturbation": report["max_perturbation"], "epsilon": preset.epsilon, "norm": preset.norm,
           "preset": preset.name, "minutes": round((time.perf_counter() - started) / 60, 2)}
    tmp = directory / "result.json.tmp"
    tmp.write_text(json.dumps(row, indent=1))
    os.replace(tmp, directory / "result.json")  # written last: the cell is finished
    return row


def _guarded(cell: Cell, preset: GridPreset, out: str) -> dict:
    """:func:`run_cell` that returns a failure row instead of raising (so one cell cannot stop a grid)."""
    try:
        return run_cell(cell, preset, out)
    except Exception as exc:  # noqa: BLE001 - recorded with its traceback and reported
        directory = cell.directory(Path(out))
        directory.mkdir(parents=True, exist_ok=True)
        (directory / "error.txt").write_text(traceback.format_exc())
        return {**asdict(cell), "error": f"{exc.__class__.__name__}: {exc}"}


def finished(cell: Cell, out: Path) -> dict | None:
    path = cell.directory(out) / "result.json"
    return json.loads(path.read_text()) if path.exists() else None


def run_grid(cells: list[Cell], preset: GridPreset, out: str | Path, jobs: int = 2, ray_address: str | None = None,
             echo: Callable[[str], None] = print, heartbeat: float = 300.0) -> dict:
    """Run every unfinished cell (RAT cells before the baselines that read their labels) and write the reports.

    Every ``heartbeat`` seconds without a finished cell, ``echo`` gets the step each running cell has reached.
    Returns ``{"ran": [...], "skipped": [...], "failed": [...], "rows": [...]}``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    record = {"preset": asdict(preset), "cells": [c.key for c in cells]}
    grid_file = out / "grid.json"
    if grid_file.exists():
        before = json.loads(grid_file.read_text())
        if before["preset"] != record["preset"]:
            raise RatError(f"'{out}' holds a grid with preset '{before['preset']['name']}' and other budgets; "
                           "give a new --out or the same preset")
        record["cells"] = sorted(set(before["cells"]) | set(record["cells"]))
    grid_file.write_text(json.dumps(record, indent=1))

    todo = [c for c in cells if finished(c, out) is None]
    skipped = [c.key for c in cells if c not in todo]
    if skipped:
        echo(f"{len(skipped)} cells already finished; {len(todo)} to run")
    first = sorted((c for c in todo if c.method not in NEEDS_LABELS), key=lambda c: c.method != "rat")  # longest first
    second = [c for c in todo if c.method in NEEDS_LABELS]
    execute = _ray_executor(ray_address, heartbeat) if ray_address else _process_executor(jobs, heartbeat)
    ran, failed = [], []
    for wave in (first, second):
        for row in execute(wave, preset, str(out)):
            if row is None:  # a heartbeat: nothing finished for a while
                running = [line for c in wave if (line := cell_progress(c, out, 2 * heartbeat))]
                echo("running: " + "; ".join(running) if running else "running: no cell has logged lately")
                continue
            (failed if "error" in row else ran).append(row)
            status = row.get("error") or f"{100 * row['attack_success_rate']:.1f}% in {row['minutes']} min"
            echo(f"[{len(ran) + len(failed)}/{len(todo)}] {Cell(row['task'], row['scenario'], row['method'], row['seed']).key}: {status}")
    rows = [r for c in cells if (r := finished(c, out)) is not None]
    write_reports(out, rows, preset)
    return {"ran": ran, "skipped": skipped, "failed": failed, "rows": rows}


def cell_progress(cell: Cell, out: Path, within: float) -> str | None:
    """``<cell>: step n/total`` for a cell whose run has logged in the last ``within`` seconds, else None."""
    run = cell.directory(out) / "run"
    metrics, config = run / "metrics.csv", run / "config.json"
    if finished(cell, out) is not None or not metrics.exists() or time.time() - metrics.stat().st_mtime > within:
        return None
    lines = metrics.read_text().splitlines()
    step = lines[-1].split(",", 1)[0] if len(lines) > 1 else "0"
    settings = json.loads(config.read_text()) if config.exists() else {}
    total = settings.get("rat", settings.get("ppo", {})).get("total_steps", "?")
    return f"{cell.key} step {step}/{total}"


def _process_executor(jobs: int, heartbeat: float):
    """Cells in ``jobs`` spawned processes; yields each result row as it finishes, None on a quiet heartbeat."""
    if jobs <= 0:
        raise RatError(f"--jobs must be positive, got {jobs}")

    def execute(cells, preset, out):
        if not cells:
            return
        if jobs == 1:
            for cell in cells:
                yield _guarded(cell, preset, out)
            return
        with ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn")) as pool:
            pending = {pool.submit(_guarded, cell, preset, out) for cell in cells}
            while pending:
                done, pending = wait(pending, timeout=heartbeat, return_when=FIRST_COMPLETED)
                yield from (future.result() for future in done) if done else [None]

    return execute


def _ray_executor(address: str, heartbeat: float):
    """Cells as Ray tasks of one CPU each on the cluster at ``address``; yields like :func:`_process_executor`."""
    ray = require("ray", "ray")

    def execute(cells, preset, out):
        if not cells:
            return
        if not ray.is_initialized():
            ray.init(address=address, log_to_driver=False)
        remote = ray.remote(num_cpus=1)(_guarded)
        pending = [remote.remote(cell, preset, out) for cell in cells]
        while pending:
            done, pending = ray.wait(pending, num_returns=1, timeout=heartbeat)
            yield ray.get(done[0]) if done else None

    return execute


# --- reports ---------------------------------------------------------------------------------------------------


def paper_row(cell_task: str, scenario: str) -> str:
    """The paper's table-1 row for a victim task in a scenario (see :data:`PAPER_TABLE1`)."""
    if scenario == "manipulation":
        return cell_task
    from rat.envs.targets import opposite_task

    return opposite_task(cell_task)


def write_reports(out: Path, rows: list[dict], preset: GridPreset) -> None:
    """``results.csv``, ``table1.md`` and ``curves-<task>.png`` from the finished cells."""
    fields = ["task", "scenario", "method", "seed", "attack_success_rate", "ci_low", "ci_high", "episodes", "labels",
              "max_perturbation", "epsilon", "norm", "preset", "minutes"]
    with open(out / "results.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fields, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(sorted(rows, key=lambda r: (r["task"], r["scenario"], METHODS.index(r["method"]), r["seed"])))
    (out / "table1.md").write_text(markdown_table(rows, preset))
    for task in sorted({r["task"] for r in rows}):
        plot_curves(out, task, [r for r in rows if r["task"] == task])


def markdown_table(rows: list[dict], preset: GridPreset) -> str:
    """Table 1's layout: a row per (scenario, task), a column per method; ours (mean ± std, n) / the paper's."""
    lines = [f"Attack success rate (%), mean ± std over seeds (n), {preset.episodes} episodes per seed; "
             f"ε = {preset.epsilon} ({preset.norm}, raw observation units); preset `{preset.name}`. "
             "Each cell: **ours** / paper (v2 tasks, 10⁶ steps).", "",
             "| scenario | victim task (paper row) | " + " | ".join(METHOD_NAMES[m] for m in METHODS) + " |",
             "| --- | --- |" + " ---: |" * len(METHODS)]
    for scenario in SCENARIOS:
        for task in sorted({r["task"] for r in rows if r["scenario"] == scenario}):
            row_task = paper_row(task, scenario)
            paper = PAPER_TABLE1.get((scenario, row_task), {})
            cells = []
            for method in METHODS:
                values = [100 * r["attack_success_rate"] for r in rows
                          if (r["task"], r["scenario"], r["method"]) == (task, scenario, method)]
                ours = f"**{np.mean(values):.1f} ± {np.std(values):.1f}** ({len(values)})" if values else "–"
                theirs = f"{paper[method][0]:.1f}" if method in paper else "–"
                cells.append(f"{ours} / {theirs}")
            label = task if row_task == task else f"{task} ({row_task})"
            lines.append(f"| {scenario} | {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_curves(out: Path, task: str, rows: list[dict]) -> Path | None:
    """Attack success during training (``eval_success_rate``), mean over seeds, per method and scenario."""
    from rat.plots import _pyplot

    plt = _pyplot()
    scenarios = [s for s in SCENARIOS if any(r["scenario"] == s for r in rows)]
    fig, axes = plt.subplots(1, len(scenarios), figsize=(6 * len(scenarios), 4), squeeze=False)
    for ax, scenario in zip(axes[0], scenarios):
        for method in METHODS:
            curves = []
            for r in rows:
                if (r["scenario"], r["method"]) != (scenario, method):
                    continue
                path = Cell(task, scenario, method, r["seed"]).directory(out) / "run" / "metrics.csv"
                if not path.exists():  # attacks without training log nothing
                    continue
                with open(path) as f:
                    points = [(int(x["step"]), float(x["eval_success_rate"])) for x in csv.DictReader(f)
                              if x.get("eval_success_rate")]
                if points:
                    curves.append(dict(points))
            if curves:
                steps = sorted(set().union(*curves))
                mean = [100 * np.mean([c[s] for c in curves if s in c]) for s in steps]
                ax.plot(steps, mean, marker="o", color=f"C{METHODS.index(method)}",  # one colour per method in every panel
                        label=f"{METHOD_NAMES[method]} (n={len(curves)})")
        ax.set(title=f"{task}: {scenario}", xlabel="environment steps", ylabel="attack success (%)", ylim=(-5, 105))
        ax.grid(alpha=0.3)
        if ax.get_lines():
            ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / f"curves-{task}.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
