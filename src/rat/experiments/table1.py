"""The paper's table 1 on one command: a resumable grid of task × scenario × method × seed.

Every cell trains one attack against the zoo victim of its task (``zoo:<task>``; a task may also
name a zoo Decision Transformer, ``dt/halfcheetah-v5``) and evaluates it over 30 episodes; its directory is ``<out>/cells/<task>/<scenario>/<method>/seed<k>/``, and the cell is
finished when its ``result.json`` exists (written last, atomically), so re-running a grid skips
finished cells and resumes interrupted ones from their checkpoints.

Methods are the paper's columns: ``pa-ad-oracle``, ``pa-ad``, ``sa-rl-oracle``, ``sa-rl``,
``random``, ``rat`` — or any registered attack (``<name>-oracle`` for its oracle variant). Those
that learn from labels, other than RAT, learn r̂ from the label store of the ``rat`` cell with
the same task, scenario and seed, so they run after it. Scenarios are ``manipulation`` (the
``reach`` target), ``opposite``, or the name of any registered target behaviour.

Cells run in parallel local processes, or as Ray tasks on a cluster given its address
(``pip install 'rat[ray]'``). Budgets come from a :class:`GridPreset` and are recorded in
``grid.json`` beside the results: ``results.csv`` (every number), ``table1.md`` (laid out like
the paper's table 1, the paper's figure beside ours) and ``curves-<task>.png``.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from rat.errors import RatError
from rat.experiments.grid import executor, guarded
from rat.experiments.paper import PAPER_TABLE1
from rat.experiments.presets import GridPreset
from rat.runs import config_differences, read_run_config

METHODS = ("pa-ad-oracle", "pa-ad", "sa-rl-oracle", "sa-rl", "random", "rat")  # the paper's column order
METHOD_NAMES = {"pa-ad-oracle": "PA-AD (oracle)", "pa-ad": "PA-AD", "sa-rl-oracle": "SA-RL (oracle)",
                "sa-rl": "SA-RL", "random": "Random", "rat": "RAT"}
SCENARIOS = {"manipulation": "reach", "opposite": "opposite"}  # the paper's scenario -> target behaviour
ADOPTED = "adopted.json"  #: in a cell's directory: the ``rat attack train`` run it took in (see adopt_run)


def scenario_target(scenario: str) -> str:
    """The target behaviour of a scenario: the paper's two, or a registered target named directly."""
    return SCENARIOS.get(scenario, scenario)


def needs_labels(method_key: str) -> bool:
    """Whether a column learns from the labels of the RAT cell beside it."""
    method, reward = column(method_key)
    return method != "rat" and reward == "labels"


def method_order(method_key: str) -> tuple[int, str]:
    """The paper's column order, then other attacks by name."""
    return (METHODS.index(method_key) if method_key in METHODS else len(METHODS), method_key)

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

    @classmethod
    def from_key(cls, key: str) -> Cell:
        task, scenario, method, seed = key.rsplit("/", 3)  # a task may hold a slash (dt/halfcheetah-v5)
        return cls(task, scenario, method, int(seed.removeprefix("seed")))

    def label_source(self) -> Cell:
        """The RAT cell whose labels a preference-based baseline learns from."""
        return Cell(self.task, self.scenario, "rat", self.seed)


def grid_cells(tasks: Iterable[str], scenarios: Iterable[str], methods: Iterable[str], seeds: Iterable[int]) -> list[Cell]:
    from rat.envs import check_task
    from rat.victims.zoo import DT_PREFIX, zoo_dt_path

    tasks, scenarios, methods, seeds = list(tasks), list(scenarios), list(methods), list(seeds)
    for task in tasks:
        zoo_dt_path(task) if task.startswith(DT_PREFIX) else check_task(task)
    from rat.attacks import check_reward, get_attack
    from rat.envs import get_target

    for scenario in scenarios:
        if scenario not in SCENARIOS:
            try:
                get_target(scenario)
            except RatError:
                raise RatError(f"unknown scenario '{scenario}'; use {', '.join(SCENARIOS)} or a registered target "
                               "(`rat list targets`)") from None
    for key in methods:
        method, reward = column(key)
        try:
            check_reward(get_attack(method), reward)
        except RatError:
            raise RatError(f"unknown method '{key}'; use some of: {', '.join(METHODS)}, or a registered attack "
                           "(`rat list attacks`), with -oracle for its oracle variant") from None
    if any(s < 0 for s in seeds) or not (tasks and scenarios and methods and seeds):
        raise RatError("a grid needs at least one task, scenario, method and seed (seeds >= 0)")
    return [Cell(t, s, m, k) for t in tasks for s in scenarios for m in methods for k in seeds]


def column(key: str) -> tuple[str, str]:
    """A table column's attack and reward source: ``<method>-oracle`` learns from the true target
    reward, ``<method>`` from the reward source the attack names first (labels for RAT, SA-RL, PA-AD)."""
    from rat.attacks import get_attack

    if key.endswith("-oracle"):
        return key[: -len("-oracle")], "oracle"
    try:
        return key, get_attack(key).rewards[0]
    except RatError:
        return key, "none"  # not an attack: grid_cells names the problem


def run_cell(cell: Cell, preset: GridPreset, out: str | Path, plugins: tuple[str, ...] = ()) -> dict:
    """Train and evaluate one cell (resuming it if interrupted); returns its result row.

    ``plugins`` are imported first (a spawned process or a Ray worker starts without them).
    """
    import torch

    from rat.plugins import load_plugins

    load_plugins(plugins)
    from rat.attacks import ThreatModel
    from rat.experiments.runner import attack_setup, train_attack

    torch.set_num_threads(1)  # one core per cell; cells run side by side
    directory = cell.directory(Path(out))
    target = scenario_target(cell.scenario)
    method, reward = column(cell.method)
    started = time.perf_counter()
    labels = None
    if method != "rat" and reward == "labels":
        labels = cell.label_source().directory(Path(out)) / "run"
        labels = labels if preset.baseline_reward == "rat" else labels / "labels.sqlite"
        if finished(cell.label_source(), Path(out)) is None:
            raise RatError(f"cell {cell.key} needs the labels of {cell.label_source().key}, which has not run")
    setup = attack_setup(f"zoo:{cell.task}", target, ThreatModel(preset.epsilon, preset.norm), cell.seed, reward,
                         labels, progress=False)
    report = train_attack(method, setup, cell_config(cell, preset), directory / "run")
    row = {**asdict(cell), "attack_success_rate": report.attack_success_rate,
           "ci_low": report.attack_success_ci[0], "ci_high": report.attack_success_ci[1],
           "episodes": report.episodes, "labels": report.labels,
           "max_perturbation": report.max_perturbation, "epsilon": preset.epsilon, "norm": preset.norm,
           "preset": preset.name, "minutes": round((time.perf_counter() - started) / 60, 2),
           "train_minutes": report.train_minutes,  # every session's, where the cell resumed
           "victim": setup.victim.name, "victim_method": setup.victim.meta.get("method", "?"),
           "last_attack_success_rate": report.details.get("last_attack_success_rate", report.attack_success_rate),
           "network_attack_success_rate": report.details.get("network_attack_success_rate"),  # when Δ is refined
           "refined_gap": report.details.get("refined_gap"),  # what refinement left of ‖μ_ν(s̃) − π_θ(s)‖
           "clean_success_rate": report.clean_success_rate}
    if (directory / ADOPTED).exists():  # trained outside the grid, by `rat attack train` (see adopt_run)
        adopted = json.loads((directory / ADOPTED).read_text())
        row["adopted_from"] = adopted.get("named", adopted["run"])  # as the command named it, not this machine's path
    tmp = directory / "result.json.tmp"
    tmp.write_text(json.dumps(row, indent=1))
    os.replace(tmp, directory / "result.json")  # written last: the cell is finished
    return row


def cell_config(cell: Cell, preset: GridPreset):
    """The configuration a cell's attack trains with under ``preset``."""
    from rat.attacks import get_attack
    from rat.attacks.rl import PPOConfig
    from rat.experiments.runner import attack_config

    method, _ = column(cell.method)
    if method == "rat":
        return attack_config("rat", preset.rat_preset, preset.labels_for(cell), preset.rat_steps,
                             scenario_target(cell.scenario), epsilon=preset.epsilon, norm=preset.norm, seed=cell.seed,
                             pebble_overrides=preset.pebble_overrides, spend_by=preset.spend_by,
                             final_eval_episodes=preset.episodes, **preset.overrides)
    attack = get_attack(method)
    fields = {f.name for f in dataclasses.fields(attack.config)} if attack.config else set()
    overrides = {"final_eval_episodes": preset.episodes} if "final_eval_episodes" in fields else {}
    steps = preset.ppo_steps if attack.config is PPOConfig else None
    return attack_config(method, preset.ppo_preset, steps=steps, **overrides)


def adopt_run(run: str | Path, cells: list[Cell], preset: GridPreset, out: str | Path) -> Cell:
    """Take a finished ``rat attack train`` run into the grid as the RAT cell it is, instead of training that cell.

    The run must be RAT against ``zoo:<task>`` of one of ``cells``, with the configuration that cell would
    train with (settings that change nothing computed, such as ``checkpoint_every``, may differ): then it *is*
    that cell's run, and it is copied into the cell's directory, where the grid evaluates it like a resumed cell
    and its labels serve the preference-based baselines. The cell's row names the run (``adopted_from``).
    Anything else is refused in one line, and nothing is copied. A run the cell took in before is left as it is.
    """
    import shutil

    from rat.attacks import ThreatModel
    from rat.attacks.rat import as_run
    from rat.experiments.runner import attack_setup
    from rat.reports import AttackReport
    from rat.runs import differences_from_run

    run, out = Path(run), Path(out)
    saved = read_run_config(run)
    if not (run / "report.json").exists():
        raise RatError(f"the run in '{run}' has not finished (no report.json); resume it with its own command first")
    done = AttackReport.read(run)
    matches = [c for c in cells if column(c.method)[0] == "rat" and f"zoo:{c.task}" == saved.get("victim")
               and scenario_target(c.scenario) == done.target and c.seed == done.seed
               and column(c.method)[1] == done.reward]
    if "rat" not in saved or not matches:
        raise RatError(f"'{run}' ({done.method} against {saved.get('victim')}, target {done.target}, "
                       f"seed {done.seed}) is no RAT cell of this grid; name its task, scenario and seed")
    cell = matches[0]
    adopted, copy = cell.directory(out) / ADOPTED, cell.directory(out) / "run"
    again = adopted.exists() and json.loads(adopted.read_text())["run"] == str(run.resolve())
    if again and copy.exists():
        return cell  # taken in before: the same command again resumes the grid
    if cell.directory(out).exists() and not again:
        raise RatError(f"cell {cell.key} already has a run in '{cell.directory(out)}'; adopt into a new --out, "
                       "or remove that cell's directory")
    setup = attack_setup(f"zoo:{cell.task}", scenario_target(cell.scenario), ThreatModel(preset.epsilon, preset.norm),
                         cell.seed, column(cell.method)[1], progress=False)
    env = setup.make_env(cell.seed)
    config = as_run(cell_config(cell, preset), env)
    env.close()
    differences = differences_from_run(run, {"rat": config, **setup.describe})
    if differences:
        raise RatError(f"'{run}' was not trained as cell {cell.key} of this grid would be (differs in: "
                       f"{'; '.join(differences)}); run that cell in the grid instead")
    cell.directory(out).mkdir(parents=True, exist_ok=True)
    adopted.write_text(json.dumps({"run": str(run.resolve()), "named": str(run)}, indent=1))  # named: for the table
    partial = copy.with_name("run.adopting")  # renamed when whole: an interrupted copy is made again
    shutil.rmtree(partial, ignore_errors=True)
    shutil.copytree(run, partial, ignore=shutil.ignore_patterns("run.lock", "*.tmp"))
    os.replace(partial, copy)
    return cell


def _guarded(cell: Cell, preset: GridPreset, out: str, plugins: tuple[str, ...] = ()) -> dict:
    """:func:`run_cell`, a failure row in its place if it raises (so one cell cannot stop a grid)."""
    row = guarded(run_cell, cell, cell.directory(Path(out)), preset, out, plugins)
    return {**asdict(cell), **row} if "error" in row else row


def finished(cell: Cell, out: Path) -> dict | None:
    path = cell.directory(out) / "result.json"
    return json.loads(path.read_text()) if path.exists() else None


def run_grid(cells: list[Cell], preset: GridPreset, out: str | Path, jobs: int = 2, ray_address: str | None = None,
             echo: Callable[[str], None] = print, heartbeat: float = 300.0, plugins: tuple[str, ...] = (),
             adopt: Iterable[str | Path] = ()) -> dict:
    """Run every unfinished cell (RAT cells before the baselines that read their labels) and write the reports.

    The reports (``results.csv``, ``table1.md``, curves) cover every finished cell the directory's grid
    has held (``grid.json``), so a grid can grow one method or seed at a time.
    Every ``heartbeat`` seconds without a finished cell, ``echo`` gets the step each running cell has reached.
    ``plugins`` (see :mod:`rat.plugins`) are imported in every process that runs cells. ``adopt`` names finished
    ``rat attack train`` runs that are RAT cells of this grid (see :func:`adopt_run`), taken in before it runs.
    Returns ``{"ran": [...], "skipped": [...], "failed": [...], "rows": [...]}``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    record = {"preset": asdict(preset), "cells": [c.key for c in cells]}
    grid_file = out / "grid.json"
    if grid_file.exists():
        before = read_grid(out)
        defaults = {f.name: f.default for f in dataclasses.fields(GridPreset) if f.default is not dataclasses.MISSING}
        if config_differences(before["preset"], record["preset"], defaults):  # settings added since match at defaults
            raise RatError(f"'{out}' holds a grid with preset '{before['preset']['name']}' and other budgets; "
                           "give a new --out or the same preset")
        record["cells"] = sorted(set(before["cells"]) | set(record["cells"]))
    grid_file.write_text(json.dumps(record, indent=1))
    for run in adopt:
        echo(f"{adopt_run(run, cells, preset, out).key}: adopted '{run}'")

    todo = [c for c in cells if finished(c, out) is None]
    skipped = [c.key for c in cells if c not in todo]
    if skipped:
        echo(f"{len(skipped)} cells already finished; {len(todo)} to run")
    first = sorted((c for c in todo if not needs_labels(c.method)), key=lambda c: c.method != "rat")  # longest first
    second = [c for c in todo if needs_labels(c.method)]
    execute = executor(jobs, ray_address, heartbeat)
    ran, failed = [], []
    for wave in (first, second):
        for row in execute(_guarded, wave, preset, str(out), tuple(plugins)):
            if row is None:  # a heartbeat: nothing finished for a while
                running = [line for c in wave if (line := cell_progress(c, out, 2 * heartbeat))]
                echo("running: " + "; ".join(running) if running else "running: no cell has logged lately")
                continue
            (failed if "error" in row else ran).append(row)
            status = row.get("error") or (f"{100 * row['attack_success_rate']:.1f}% in {row['minutes']} min here "
                                          f"({row['train_minutes']} min of training over every session)")
            echo(f"[{len(ran) + len(failed)}/{len(todo)}] {Cell(row['task'], row['scenario'], row['method'], row['seed']).key}: {status}")
    return {"ran": ran, "skipped": skipped, "failed": failed, "rows": grid_reports(out)}


def read_grid(out: str | Path) -> dict:
    """The record of the grid in ``out`` (its ``grid.json``, as written): ``preset`` (the budgets, a dict) and
    ``cells`` (every cell key the directory has held); a missing or damaged record is refused in one line."""
    grid_file = Path(out) / "grid.json"
    if not grid_file.exists():
        raise RatError(f"'{out}' holds no grid (no grid.json); give the --out of a grid `rat bench table1` ran")
    try:
        record = json.loads(grid_file.read_text())
        record_preset(record)
        if not all(isinstance(key, str) for key in record["cells"]):
            raise TypeError("a cell key is not a string")
        return record
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise RatError(f"'{grid_file}' is not a grid record ({exc.__class__.__name__}: {exc}); "
                       "restore it or run the grid into a new --out") from None


def record_preset(record: dict) -> GridPreset:
    """The :class:`GridPreset` of a grid record (settings it no longer has are left out)."""
    known = {f.name for f in dataclasses.fields(GridPreset)}
    return GridPreset(**{k: v for k, v in record["preset"].items() if k in known})


def grid_reports(out: str | Path) -> list[dict]:
    """Write the reports of the grid in ``out`` from every cell its ``grid.json`` has held that has finished
    (a grid stopped part-way included); runs nothing. Returns the finished cells' rows."""
    out = Path(out)
    record = read_grid(out)
    rows = [r for key in record["cells"] if (r := finished(Cell.from_key(key), out)) is not None]
    write_reports(out, rows, record_preset(record))
    return rows


def cell_progress(cell: Cell, out: Path, within: float) -> str | None:
    """``<cell>: step n/total`` for a cell whose run has logged in the last ``within`` seconds, else None."""
    run = cell.directory(out) / "run"
    metrics = run / "metrics.csv"
    if finished(cell, out) is not None or not metrics.exists() or time.time() - metrics.stat().st_mtime > within:
        return None
    lines = metrics.read_text().splitlines()
    step = lines[-1].split(",", 1)[0] if len(lines) > 1 else "0"
    try:
        settings = read_run_config(run)
    except RatError:  # not written yet, or damaged: the cell's own run says so; a progress line should not stop a grid
        settings = {}
    total = settings.get("rat", settings.get("ppo", {})).get("total_steps", "?")
    return f"{cell.key} step {step}/{total}"


# --- reports ---------------------------------------------------------------------------------------------------


def paper_row(cell_task: str, scenario: str) -> str:
    """The paper's table-1 row for a victim task in a scenario (see :data:`PAPER_TABLE1`)."""
    if scenario != "opposite":
        return cell_task
    from rat.envs.targets import opposite_task

    return opposite_task(cell_task)


def write_reports(out: Path, rows: list[dict], preset: GridPreset) -> None:
    """``results.csv``, ``table1.md`` and ``curves-<task>.png`` from the finished cells."""
    fields = ["task", "scenario", "method", "seed", "attack_success_rate", "ci_low", "ci_high", "episodes", "labels",
              "max_perturbation", "epsilon", "norm", "preset", "minutes", "train_minutes", "victim", "victim_method",
              "last_attack_success_rate", "network_attack_success_rate", "refined_gap", "clean_success_rate",
              "adopted_from"]
    with open(out / "results.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fields, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(sorted(rows, key=lambda r: (r["task"], r["scenario"], method_order(r["method"]), r["seed"])))
    (out / "table1.md").write_text(markdown_table(rows, preset))
    for task in sorted({r["task"] for r in rows}):
        plot_curves(out, task, [r for r in rows if r["task"] == task])


def victim_kind(row: dict) -> str:
    """SAC, behaviour clone, or the victim's method as recorded (a row of a grid predating the record: –)."""
    method = str(row.get("victim_method") or "")
    return "SAC" if method.startswith("sac") else "behaviour clone" if method == "bc" else method or "–"


def markdown_table(rows: list[dict], preset: GridPreset | None = None) -> str:
    """Table 1's layout: a row per (scenario, task, victim kind), a column per method; ours (mean ± std, n) / the
    paper's. The budgets in the header are the rows' own (several where merged grids differ), else ``preset``'s."""
    methods = sorted(set(METHODS) | {r["method"] for r in rows}, key=method_order)
    scenarios = list(SCENARIOS) + sorted({r["scenario"] for r in rows} - set(SCENARIOS))

    def recorded(key: str, fallback) -> str:
        values = sorted({str(r[key]) for r in rows if r.get(key) not in (None, "")})
        return " / ".join(values) if values else str(fallback)

    lines = [f"Attack success rate (%), mean ± std over seeds (n), {recorded('episodes', preset and preset.episodes)} "
             f"episodes per seed; ε = {recorded('epsilon', preset and preset.epsilon)} "
             f"({recorded('norm', preset and preset.norm)}, raw observation units); preset "
             f"`{recorded('preset', preset and preset.name)}`. Each cell: **ours** / paper (v2 tasks, 10⁶ steps). "
             "*clean*: the unattacked victim's success at the same target, the yardstick every attack must beat.", "",
             "| scenario | victim task (paper row) | victim | labels | clean | "
             + " | ".join(METHOD_NAMES.get(m, m) for m in methods) + " |",
             "| --- | --- | --- | ---: | ---: |" + " ---: |" * len(methods)]
    for scenario in scenarios:
        groups = sorted({(r["task"], victim_kind(r)) for r in rows if r["scenario"] == scenario})
        for task, kind in groups:
            mine = [r for r in rows if (r["task"], r["scenario"], victim_kind(r)) == (task, scenario, kind)]
            row_task = paper_row(task, scenario)
            paper = PAPER_TABLE1.get((scenario, row_task), {})
            cells = []
            for method in methods:
                values = [100 * float(r["attack_success_rate"]) for r in mine if r["method"] == method]
                ours = f"**{np.mean(values):.1f} ± {np.std(values):.1f}** ({len(values)})" if values else "–"
                theirs = f"{paper[method][0]:.1f}" if method in paper else "–"
                cells.append(f"{ours} / {theirs}")
            label = task if row_task == task else f"{task} ({row_task})"
            clean = [100 * float(r["clean_success_rate"]) for r in mine if r.get("clean_success_rate") not in (None, "")]
            clean_cell = f"{np.mean(clean):.1f}" if clean else "–"
            labels = sorted({int(float(r["labels"])) for r in mine if r["method"] == "rat" and r.get("labels") not in (None, "")})
            labels_cell = " / ".join(f"{n:,}" for n in labels) or "–"  # RAT's (and the preference baselines')
            lines.append(f"| {scenario} | {label} | {kind} | {labels_cell} | {clean_cell} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def report_grid(out: str | Path) -> Path:
    """``<out>/table1.md`` generated from ``<out>/results.csv`` alone (a grid, or several merged, whose runs are
    gone): the command that regenerates a committed table."""
    path = Path(out) / "results.csv"
    if not path.exists():
        raise RatError(f"'{out}' holds no results.csv; give a folder written by `rat bench table1`")
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    missing = {"task", "scenario", "method", "seed", "attack_success_rate"} - set(rows[0] if rows else {})
    if not rows or missing:
        raise RatError(f"'{path}' is not a table-1 results file (missing: {', '.join(sorted(missing)) or 'rows'})")
    page = Path(out) / "table1.md"
    page.write_text(markdown_table(rows))
    return page


def plot_curves(out: Path, task: str, rows: list[dict]) -> Path | None:
    """Attack success during training (``eval_success_rate``), mean over seeds, per method and scenario, and a star
    at the end for the attack as deployed (the table's figure): where Δ is refined at attack time the evaluations
    during training measure the network's Δ alone, and the two can differ by 90 points."""
    from rat.plots import pyplot

    plt = pyplot()
    scenarios = sorted({r["scenario"] for r in rows}, key=lambda s: (s not in SCENARIOS, s))
    methods = sorted({r["method"] for r in rows}, key=method_order)
    colour = {m: f"C{i % 10}" for i, m in enumerate(sorted(set(METHODS) | set(methods), key=method_order))}
    fig, axes = plt.subplots(1, len(scenarios), figsize=(6 * len(scenarios), 4), squeeze=False)
    for ax, scenario in zip(axes[0], scenarios):
        for method in methods:
            curves, finals = [], []
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
                    finals.append(float(r["attack_success_rate"]))
            if curves:
                steps = sorted(set().union(*curves))
                mean = [100 * np.mean([c[s] for c in curves if s in c]) for s in steps]
                ax.plot(steps, mean, marker="o", color=colour[method],  # one colour per method in every panel
                        label=f"{METHOD_NAMES.get(method, method)} (n={len(curves)})")
                ax.plot([steps[-1]], [100 * np.mean(finals)], marker="*", markersize=13, linestyle="none",
                        color=colour[method])
        ax.set(title=f"{task}: {scenario}", xlabel="environment steps", ylabel="attack success (%)", ylim=(-5, 105))
        ax.grid(alpha=0.3)
        if ax.get_lines():
            ax.plot([], [], marker="*", markersize=10, linestyle="none", color="0.4", label="as deployed (the table)")
            ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / f"curves-{task.replace('/', '-')}.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
