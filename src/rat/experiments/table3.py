"""The paper's table 3, and beyond it: robust agents × attacks, each attack trained afresh against each agent.

A row is one defence of one task and seed (``rat-atla``, ``rat-wocar``, ``atla``, ``pa-atla``), or ``undefended``:
the zoo's SAC victim the defences start from. Each row's agent is trained by :func:`~rat.robust.run.train_robust_from`
in ``<out>/<task>/<row>-seed<seed>`` (skipped once finished, resumed if interrupted), then every attack is trained
against it in that directory's ``eval/<attack>`` (:func:`~rat.robust.run.attack_agent`). The table gives, per
attack, the task return (table 3's number) *and* the target's success rate, and per row the clean return, the price
a defence pays when nobody attacks.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from rat.attacks.threat import ThreatModel
from rat.errors import RatError
from rat.experiments.paper import PAPER_TABLE3

ROWS = ("undefended", "rat-atla", "rat-wocar", "atla", "pa-atla")
ATTACKS = ("rat", "pa-ad", "sa-rl", "random")
ROW_NAMES = {"undefended": "undefended (zoo SAC)", "rat-atla": "RAT-ATLA", "rat-wocar": "RAT-WocaR",
             "atla": "ATLA (SAC agent)", "pa-atla": "PA-ATLA (SAC agent)"}


def row_directory(out: str | Path, task: str, row: str, seed: int) -> Path:
    return Path(out) / task / f"{row}-seed{seed}"


def check_grid(rows: Iterable[str], attacks: Iterable[str]) -> None:
    from rat.attacks import get_attack

    unknown = sorted(set(rows) - set(ROWS))
    if unknown:
        raise RatError(f"unknown table-3 rows {', '.join(unknown)}; use any of {', '.join(ROWS)}")
    for attack in attacks:
        get_attack(attack)  # an unknown attack is named before anything trains


def run_row(task: str, row: str, seed: int, attacks: list[str], out: str | Path, preset: str = "cpu",
            target: str = "reach", threat: ThreatModel = ThreatModel(), episodes: int = 100,
            progress: bool = True) -> dict:
    """Train (or find) the row's agent, attack it with each attack, and write ``<row dir>/row.json``."""
    from rat.robust.run import attack_agent, finished_report, train_robust_from
    from rat.robust.trainer import robust_preset

    directory, victim = row_directory(out, task, row, seed), f"zoo:{task}@sac"
    record = {"task": task, "row": row, "seed": seed, "target": target, "epsilon": threat.epsilon,
              "norm": threat.norm, "preset": preset}
    if row == "undefended":
        agent = victim
    else:
        if not (directory / "report.json").exists():
            train_robust_from(robust_preset(preset, method=row, seed=seed), victim, target, directory, preset,
                              threat=threat, progress=progress)
        report = finished_report(directory)
        agent = str(directory)
        record |= {"train_minutes": report["train_minutes"], "clean_task_success": report["clean_task_success"]}
    table = attack_agent(agent, directory / "eval", target, threat, attacks, preset, None, episodes, seed, progress)
    record |= {"clean_return": table["clean_return"], "clean_return_std": table["clean_return_std"],
               "attacks": table["attacks"]}
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "row.json").write_text(json.dumps(record, indent=1))
    return record


def run_table3(tasks: list[str], rows: list[str], attacks: list[str], seeds: list[int], out: str | Path,
               preset: str = "cpu", target: str = "reach", threat: ThreatModel = ThreatModel(), episodes: int = 100,
               echo: Callable[[str], None] = print, progress: bool = True) -> list[dict]:
    """Every (task, seed, row) in turn, finished parts skipped; then ``<out>/table3.md`` from every finished row."""
    check_grid(rows, attacks)
    for task in tasks:
        for seed in seeds:
            for row in rows:
                echo(f"{task} seed {seed}: {row}")
                run_row(task, row, seed, attacks, out, preset, target, threat, episodes, progress)
    return write_table3(out)


def finished_rows(out: str | Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(Path(out).glob("*/*-seed*/row.json"))]


def write_table3(out: str | Path) -> list[dict]:
    """``<out>/table3.md`` and ``<out>/results.json`` from the finished rows under ``out``."""
    rows = finished_rows(out)
    Path(out).mkdir(parents=True, exist_ok=True)
    (Path(out) / "results.json").write_text(json.dumps(rows, indent=1))
    (Path(out) / "table3.md").write_text(markdown_table3(rows))
    return rows


def pooled(means: list[float], stds: list[float]) -> tuple[float, float]:
    """Mean and std of the episodes of several seeds, each given by its episodes' mean and std (equal counts)."""
    mean = float(np.mean(means))
    return mean, float(np.sqrt(np.mean([s ** 2 + (m - mean) ** 2 for m, s in zip(means, stds)])))


def markdown_table3(rows: list[dict]) -> str:
    """Per task: a line per row; per attack the task return (mean ± std over episodes, seeds pooled), the target's
    success (%), and the paper's return; the clean return; the mean of the attacks' returns (random's left out)."""
    attacks = [a for a in ATTACKS if any(a in r["attacks"] for r in rows)]
    attacks += sorted({a for r in rows for a in r["attacks"]} - set(attacks))
    lines = ["Task return under each attack, mean ± std over the episodes (seeds pooled; n seeds), the target's "
             "success rate in brackets, then the paper's return (table 3; its ATLA-PPO and PA-ATLA are PPO agents, "
             "ours SAC). *clean*: the agent unattacked, what robustness costs. *avg R*: the mean of the attacks' "
             "returns, random's left out as in the paper, and the paper's.", ""]
    for task in sorted({r["task"] for r in rows}):
        first = next(r for r in rows if r["task"] == task)
        lines += [f"### {task} (target `{first['target']}`, ε = {first['epsilon']} {first['norm']}, preset "
                  f"`{first['preset']}`)", "",
                  "| row | n | clean | " + " | ".join(attacks) + " | avg R / paper |",
                  "| --- | ---: | ---: |" + " --- |" * len(attacks) + " ---: |"]
        for name in ROWS:
            mine = [r for r in rows if (r["task"], r["row"]) == (task, name)]
            if not mine:
                continue
            paper = PAPER_TABLE3.get(task, {}).get(name, {})
            cells, averages = [], []
            for attack in attacks:
                cols = [r["attacks"][attack] for r in mine if attack in r["attacks"]]
                if not cols:
                    cells.append("–")
                    continue
                mean, std = pooled([c["return"] for c in cols], [c["return_std"] for c in cols])
                success = 100 * np.mean([c["target_success"] for c in cols])
                theirs = f" / {paper[attack][0]:.0f}" if attack in paper else ""
                cells.append(f"**{mean:.0f} ± {std:.0f}** ({success:.0f}%){theirs}")
                averages += [mean] * (attack != "random")
            clean = pooled([r["clean_return"] for r in mine], [r["clean_return_std"] for r in mine])
            average = f"{np.mean(averages):.0f}" if averages else "–"
            if paper:
                average += f" / {np.mean([v[0] for v in paper.values()]):.0f}"
            lines.append(f"| {ROW_NAMES[name]} | {len(mine)} | {clean[0]:.0f} ± {clean[1]:.0f} | "
                         + " | ".join(cells) + f" | {average} |")
        lines.append("")
    return "\n".join(lines)
