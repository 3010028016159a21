"""Does the intention policy learn the target, and keep it? `rat intention train` on a grid of targets,
oracle and labels, several seeds: success every 10k steps and at the end.

Each cell is the command a user would run, with the intention-policy settings of the `cpu` preset
of a RAT run for that target, passed as ``--set`` wherever they differ from PEBBLE's defaults (SAC batch
256, at most 30 reward epochs and 400 updates a member a round, the label budget spent in equal rounds
every 5,000 steps by 90% of the run; for reach also standardised r̂ inputs and queries from the last
20 episodes); the default rows take the paper's label counts. Cells run as subprocesses, ``--jobs`` at a time, one
torch thread each; a finished cell (its ``report.json``) is skipped, an unfinished one resumes, so
the grid can span sessions.

    python benchmarks/intention_grid.py --out runs/intention-grid                   # the default grid
    python benchmarks/intention_grid.py --rows drawer-open-v3:reach:9000 --seeds 0 --modes oracle
    python benchmarks/intention_grid.py --out runs/intention-grid --table-only      # just the table

A row is ``victim-task:target:labels``; the table says, per cell, the success at each evaluation,
the 30-episode final success, and whether the behaviour, once reached (an evaluation at ≥ 50%),
was kept to the end (final success at least half the peak), and the lowest evaluation after it was
first reached (a behaviour lost for a while and found again).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from rat.experiments.presets import rat_config
from rat.preferences.pebble import PebbleConfig

#: reach (the manipulation target) and two opposite behaviours (drawer-close, faucet-open), at the paper's label counts
DEFAULT_ROWS = ("drawer-open-v3:reach:9000", "drawer-open-v3:opposite:3000", "faucet-close-v3:opposite:5000")
REACHED, KEPT = 0.5, 0.5


def preset_assignments(config, default, prefix: str = "pebble") -> list[str]:
    """``--set`` assignments for every field in which ``config`` differs from ``default`` (nested groups too)."""
    out = []
    for f in dataclasses.fields(config):
        value, base = getattr(config, f.name), getattr(default, f.name)
        if dataclasses.is_dataclass(value):
            out += preset_assignments(value, base, f"{prefix}.{f.name}")
        elif value != base:
            text = "none" if value is None else json.dumps(value) if isinstance(value, (bool, list, tuple, dict)) else value
            out += ["--set", f"{prefix}.{f.name}={text}"]
    return out


def command(task: str, target: str, labels: int, mode: str, seed: int, steps: int, out: Path) -> list[str]:
    """The `rat intention train` command of one cell: every PEBBLE setting of the `cpu` preset for this target
    that differs from PEBBLE's defaults (SAC batch, reward-round caps, rounds, and the manipulation settings)."""
    oracle = mode == "oracle"
    pebble = rat_config("cpu", budget=0 if oracle else labels, steps=steps, target=target).pebble
    cmd = [sys.executable, "-m", "rat.cli", "intention", "train", "--task", task, "--target", target, "--steps", str(steps),
           "--seed", str(seed), "--out", str(out), *preset_assignments(pebble, PebbleConfig())]
    return cmd + (["--oracle"] if oracle else [])


def cell_dir(out: Path, task: str, target: str, labels: int, mode: str, seed: int) -> Path:
    return out / f"{task}-{target}-{mode}{'' if mode == 'oracle' else labels}-seed{seed}"


def run_cell(cmd: list[str], directory: Path) -> tuple[Path, int, float]:
    if (directory / "report.json").is_file():
        return directory, 0, 0.0
    directory.parent.mkdir(parents=True, exist_ok=True)
    env = os.environ | {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    started = time.perf_counter()
    with open(directory.parent / f"{directory.name}.log", "ab") as log:
        code = subprocess.call(["nice", "-n", "5", *cmd], stdout=log, stderr=subprocess.STDOUT, env=env)
    return directory, code, (time.perf_counter() - started) / 60


def curve(directory: Path) -> list[tuple[int, float]]:
    path = directory / "metrics.csv"
    if not path.is_file():
        return []
    with open(path) as f:
        return [(int(r["step"]), float(r["eval_success_rate"])) for r in csv.DictReader(f) if r.get("eval_success_rate")]


def table(cells: list[tuple[str, str, int, str, int, Path]]) -> str:
    lines = ["| victim task | target | reward | seed | success during training (10 ep.) | final (30 ep.) | reached | "
             "lowest after | kept | minutes |", "| --- | --- | --- | ---: | --- | ---: | --- | ---: | --- | ---: |"]
    for task, target, labels, mode, seed, directory in cells:
        points = curve(directory)
        report = directory / "report.json"
        final = json.loads(report.read_text()) if report.is_file() else None
        peak = max((s for _, s in points), default=0.0)
        reached = next((step for step, s in points if s >= REACHED), None)
        after = [s for step, s in points if reached is not None and step > reached]
        done = final is not None
        state = "running" if directory.is_dir() else "not started"
        kept = "–" if not done or reached is None else ("yes" if final["target_success_rate"] >= KEPT * peak else "**no**")
        lines.append(
            f"| {task} | {target} | {'oracle' if mode == 'oracle' else f'{labels} labels'} | {seed} | "
            + (", ".join(f"{step // 1000}k: {100 * s:.0f}%" for step, s in points) or "–") + " | "
            + (f"{100 * final['target_success_rate']:.1f}%" if done else state) + " | "
            + (f"{reached // 1000}k" if reached is not None else "never" if done else "not yet") + " | "
            + (f"{100 * min(after):.0f}%" if after else "–") + f" | {kept} | "
            + (f"{final['train_minutes']:.0f}" if done else "–") + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", default=",".join(DEFAULT_ROWS), help="comma-separated victim-task:target:labels")
    parser.add_argument("--modes", default="oracle,labels")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--steps", type=int, default=50_000)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("runs/intention-grid"))
    parser.add_argument("--table-only", action="store_true", help="write the table from the cells finished so far")
    args = parser.parse_args()
    cells = []
    for row in args.rows.split(","):
        parts = row.split(":")
        if len(parts) != 3 or not parts[2].isdigit():
            parser.error(f"row '{row}' is not victim-task:target:labels (e.g. drawer-open-v3:reach:9000)")
        task, target, labels = parts
        for mode in args.modes.split(","):
            for seed in map(int, args.seeds.split(",")):
                cells.append((task, target, int(labels), mode, seed,
                              cell_dir(args.out, task, target, int(labels), mode, seed)))
    if not args.table_only:
        with ThreadPoolExecutor(args.jobs) as pool:
            jobs = [pool.submit(run_cell, command(t, g, n, m, s, args.steps, d), d) for t, g, n, m, s, d in cells]
            for job in jobs:
                directory, code, minutes = job.result()
                said = "done" if code == 0 else f"exit {code}, see {directory.parent / directory.name}.log"
                print(f"{directory.name}: {said} ({minutes:.1f} min)", flush=True)
    text = table(cells)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "intention-grid.md").write_text(text)
    sys.stdout.write(text)


if __name__ == "__main__":
    main()
