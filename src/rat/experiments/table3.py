"""The paper's table 3, and beyond it: robust agents × attacks, each attack trained afresh against each agent.

A row is one defence of one task and seed (``rat-atla``, ``rat-wocar``, ``atla``, ``pa-atla``, and
``rat-wocar-worst``: RAT-WocaR with WocaR's worst-case estimate in place of the release's term), ``undefended``:
the zoo's SAC victim the defences start from (:func:`~rat.victims.zoo.sac_victim`), or ``none``: that victim
trained on as the defences are, with no defence (the control, which tells what a defence does beyond the
fine-tuning every row gets). Each row's agent is trained by :func:`~rat.robust.run.train_robust_from` in
``<out>/<task>/<row>-seed<seed>`` (skipped once finished, resumed if interrupted), then every attack is trained
against it in that directory's ``eval/<attack>`` (:func:`~rat.robust.run.attack_agent`): two waves of cells on
:mod:`rat.experiments.grid`, in local processes or as Ray tasks. The table gives, per attack, the task return
(table 3's number) *and* the target's success rate, and per row the clean return, the price a defence pays when
nobody attacks.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rat.attacks.threat import ThreatModel
from rat.errors import RatError
from rat.experiments.paper import PAPER_TABLE3

ROWS = ("undefended", "none", "rat-atla", "rat-wocar", "rat-wocar-worst", "atla", "pa-atla")
ATTACKS = ("rat", "pa-ad", "sa-rl", "random")
ROW_NAMES = {"undefended": "undefended (zoo SAC)", "none": "fine-tuned, no defence", "rat-atla": "RAT-ATLA",
             "rat-wocar": "RAT-WocaR", "rat-wocar-worst": "RAT-WocaR (worst-case Q)", "atla": "ATLA (SAC agent)",
             "pa-atla": "PA-ATLA (SAC agent)"}
#: The rows the defences are tested against.
BASELINES = {"undefended": "the undefended victim", "none": "the control (fine-tuned, no defence)"}
#: A row that is a method under other settings than its defaults; every other row is its method.
ROW_SETTINGS = {"rat-wocar-worst": ("rat-wocar", {"wocar_critic": "worst-case"})}


def row_config(row: str, preset: str, seed: int):
    """The :class:`~rat.robust.trainer.RobustConfig` a row's agent is trained with."""
    from rat.robust.trainer import robust_preset

    method, settings = ROW_SETTINGS.get(row, (row, {}))
    return robust_preset(preset, method=method, seed=seed, **settings)


def row_directory(out: str | Path, task: str, row: str, seed: int) -> Path:
    return Path(out) / task / f"{row}-seed{seed}"


def check_grid(rows: Iterable[str], attacks: Iterable[str]) -> None:
    from rat.attacks import get_attack

    unknown = sorted(set(rows) - set(ROWS))
    if unknown:
        raise RatError(f"unknown table-3 rows {', '.join(unknown)}; use any of {', '.join(ROWS)}")
    for attack in attacks:
        get_attack(attack)  # an unknown attack is named before anything trains


@dataclass(frozen=True)
class Agent:
    """A row's agent: the zoo victim itself (``undefended``) or the robust agent trained from it."""

    task: str
    row: str
    seed: int

    @property
    def key(self) -> str:
        return f"{self.task}/{self.row}-seed{self.seed}"

    def directory(self, out: str | Path) -> Path:
        return row_directory(out, self.task, self.row, self.seed)

    def victim(self, out: str | Path) -> str:
        """The victim spec the attacks are trained against."""
        from rat.victims.zoo import sac_victim

        return sac_victim(self.task) if self.row == "undefended" else str(self.directory(out))

    def trained(self, out: str | Path) -> bool:
        return self.row == "undefended" or (self.directory(out) / "report.json").exists()


def train_agent(agent: Agent, out: str, preset: str, target: str, epsilon: float, norm: str, progress: bool) -> dict:
    """Grid cell: train (or resume) the robust agent of ``agent``'s row."""
    import torch

    from rat.robust.run import train_robust_from
    from rat.victims.zoo import sac_victim

    torch.set_num_threads(1)  # one core per cell; cells run side by side
    report = train_robust_from(row_config(agent.row, preset, agent.seed), sac_victim(agent.task),
                               target, agent.directory(out), preset, threat=ThreatModel(epsilon, norm),
                               progress=progress)
    return {"cell": agent.key, "train_minutes": report["train_minutes"]}


def attack_cell(cell: tuple[Agent, str], out: str, preset: str, target: str, epsilon: float, norm: str,
                episodes: int, progress: bool) -> dict:
    """Grid cell: one attack trained against one row's agent, and its attacked episodes
    (``<row dir>/eval/<attack>/table-row.json``)."""
    import torch

    from rat.robust.run import attack_agent

    torch.set_num_threads(1)
    agent, attack = cell
    table = attack_agent(agent.victim(out), agent.directory(out) / "eval", target, ThreatModel(epsilon, norm),
                         [attack], preset, None, episodes, agent.seed, progress)
    return {"cell": f"{agent.key}/{attack}", **table["attacks"][attack]}


def guarded_agent(agent: Agent, *args) -> dict:
    """:func:`train_agent`, a failure row in its place if it raises (one cell cannot stop the grid)."""
    from rat.experiments.grid import guarded

    return {"cell": agent.key, **guarded(train_agent, agent, agent.directory(args[0]), *args)}


def guarded_attack(cell: tuple[Agent, str], *args) -> dict:
    """:func:`attack_cell`, a failure row in its place if it raises."""
    from rat.experiments.grid import guarded

    agent, attack = cell
    return {"cell": f"{agent.key}/{attack}", **guarded(attack_cell, cell, agent.directory(args[0]) / "eval" / attack, *args)}


def write_row(agent: Agent, attacks: list[str], out: str | Path, preset: str, target: str,
              threat: ThreatModel) -> dict | None:
    """``<row dir>/row.json`` from the row's finished attack cells (None until one has finished)."""
    from rat.robust.run import finished_report

    directory = agent.directory(out)
    cells = {a: json.loads(p.read_text()) for a in attacks if (p := directory / "eval" / a / "table-row.json").exists()}
    if not cells:
        return None
    first = next(iter(cells.values()))
    record = {"task": agent.task, "row": agent.row, "seed": agent.seed, "target": target, "epsilon": threat.epsilon,
              "norm": threat.norm, "preset": preset, "clean_return": first["clean_return"],
              "clean_return_std": first["clean_return_std"], "attacks": cells}
    if agent.row == "undefended":
        record["victim"] = agent.victim(out)  # which zoo victim: @sac, or the SAC-fine-tuned clone (@sac-ft)
    else:
        report = finished_report(directory)
        record |= {"train_minutes": report["train_minutes"], "clean_task_success": report["clean_task_success"]}
    (directory / "row.json").write_text(json.dumps(record, indent=1))
    return record


def run_table3(tasks: list[str], rows: list[str], attacks: list[str], seeds: list[int], out: str | Path,
               preset: str = "cpu", target: str = "reach", threat: ThreatModel = ThreatModel(), episodes: int = 100,
               echo: Callable[[str], None] = print, jobs: int = 1, ray_address: str | None = None,
               heartbeat: float = 300.0) -> list[dict]:
    """The grid in two waves, finished cells skipped and interrupted ones resumed: every row's robust agent, then
    every (agent, attack) cell, RAT's first (the longest); then ``<out>/table3.md`` from every finished row."""
    from rat.experiments.grid import executor

    check_grid(rows, attacks)
    out = str(out)
    agents = [Agent(task, row, seed) for task in tasks for seed in seeds for row in rows]
    execute = executor(jobs, ray_address, heartbeat)
    args = (out, preset, target, threat.epsilon, threat.norm)
    progress = jobs == 1 and not ray_address  # bars only where one cell runs at a time, in this process
    failed = []
    to_train = [a for a in agents if not a.trained(out)]
    echo(f"{len(to_train)} robust agents to train; then up to {len(agents) * len(attacks)} attack cells")
    for row in execute(guarded_agent, to_train, *args, progress):
        if row is not None:
            failed += [row] * ("error" in row)
            echo(f"{row['cell']}: " + (row.get("error") or f"trained, {row['train_minutes']:.1f} min"))
    cells = [(a, attack) for attack in sorted(attacks, key=lambda x: x != "rat") for a in agents
             if a.trained(out) and not (a.directory(out) / "eval" / attack / "table-row.json").exists()]
    for row in execute(guarded_attack, cells, *args, episodes, progress):
        if row is not None:
            failed += [row] * ("error" in row)
            echo(f"{row['cell']}: " + (row.get("error") or f"return {row['return']:.1f} ± {row['return_std']:.1f}, "
                                       f"target reached {100 * row['target_success']:.1f}%"))
    for agent in agents:
        write_row(agent, attacks, out, preset, target, threat)
    if failed:
        raise RatError(f"{len(failed)} table-3 cells failed (tracebacks in their error.txt); fix and re-run to resume")
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
        of_task = [r for r in rows if r["task"] == task]
        lines += ["", *against(of_task, "undefended"), *against(of_task, "none")]
    return "\n".join(lines)


def against(rows: list[dict], base: str = "undefended", attack: str = "rat") -> list[str]:
    """Each other defended row of one task against row ``base`` (the undefended victim, or the ``none`` control)
    under ``attack``: the task return (Welch's one-sided t-test that the defence's is higher, from the pooled means
    and stds) and the target's success (Fisher's exact one-sided test that it is lower), with the minutes its agent
    took to train."""
    from scipy import stats

    def pooled_cell(name):
        cells = [(r["attacks"][attack], r) for r in rows if r["row"] == name and attack in r["attacks"]]
        if not cells:
            return None
        mean, std = pooled([c["return"] for c, _ in cells], [c["return_std"] for c, _ in cells])
        n = sum(c["episodes"] for c, _ in cells)
        hits = round(sum(c["target_success"] * c["episodes"] for c, _ in cells))
        minutes = [r["train_minutes"] for _, r in cells if "train_minutes" in r]
        return mean, std, n, hits, minutes

    reference = pooled_cell(base)
    defended = [(name, cell) for name in ROWS if name not in ("undefended", base) and (cell := pooled_cell(name))]
    if reference is None or not defended:
        return []
    lines = [f"Against {BASELINES[base]} under {attack} (return higher: Welch, one-sided; target reached less: "
             "Fisher, one-sided):", "",
             "| row | return | p (higher) | target reached | p (less) | minutes to train |",
             "| --- | ---: | ---: | ---: | ---: | ---: |",
             f"| {ROW_NAMES[base]} | {reference[0]:.0f} | | {reference[3]}/{reference[2]} | | |"]
    for name, (mean, std, n, hits, minutes) in defended:
        p_return = stats.ttest_ind_from_stats(mean, std, n, reference[0], reference[1], reference[2],
                                              equal_var=False, alternative="greater").pvalue
        p_target = stats.fisher_exact([[hits, n - hits], [reference[3], reference[2] - reference[3]]],
                                      alternative="less").pvalue
        took = ", ".join(f"{m:.0f}" for m in minutes) or "–"
        lines.append(f"| {ROW_NAMES[name]} | {mean:.0f} | {p_return:.2g} | {hits}/{n} | {p_target:.2g} | {took} |")
    return lines + [""]
