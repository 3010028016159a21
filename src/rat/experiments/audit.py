"""``rat audit``: how robust is *this* agent? Every attack, every target and budget ε, in one resumable folder
and one page.

For each target and ε the audit trains (or finds) each attack, cheapest first — ``random``, ``mad``, the
white-box ``probe`` (where the target has a steering), ``sa-rl`` on the true target reward, ``rat`` from labels —
in ``<out>/<target>/eps<ε>/<attack>``, and records its final evaluation: target success with its 95% interval,
the task return attacked and clean, the perturbation sizes. Cells go in rounds, one attack at every ε before the
next attack, so a short budget still measures the cheap attacks everywhere. The budget is checked before each
cell: a cell is skipped when the time left is below what the same attack took at an earlier ε, and none starts
once the budget is spent; a cell started is finished (and an interrupted audit resumes its cells). What did
not run is said, with why, in ``audit.json`` and on the page (``report.html``, with ``audit.png``).
"""

from __future__ import annotations

import csv
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rat.attacks.base import AttackSetup, get_attack, measured_reward
from rat.errors import RatError
from rat.reports import AttackReport

AUDIT_ATTACKS = ("random", "mad", "probe", "sa-rl", "rat")  #: cheapest first
FIELDS = ["target", "epsilon", "attack", "reward", "status", "attack_success_rate", "ci_low", "ci_high",
          "attacked_return", "clean_success_rate", "clean_return", "max_perturbation", "mean_perturbation", "episodes",
          "minutes", "why"]


def check_audit(epsilons: list[float], budget_minutes: float, attacks: list[str]) -> None:
    """One line for each way an audit's request cannot be met, before anything runs."""
    if not epsilons or any(not e > 0 for e in epsilons):
        raise RatError(f"--epsilons must be budgets > 0 (e.g. 0.02,0.05,0.1), got {','.join(map(str, epsilons)) or 'none'}")
    if not budget_minutes >= 1:
        raise RatError(f"a budget of {budget_minutes:g} minutes runs no attack (even the random one evaluates for about "
                       "a minute on a Meta-World task); give --budget-minutes 1 or more")
    for attack in attacks:
        get_attack(attack)  # an unknown one is named before anything runs


def run_audit(setup_for: Callable[[str, float, str], AttackSetup], config_for: Callable[[str, str], Any],
              targets: list[str], epsilons: list[float], out: str | Path, budget_minutes: float,
              attacks: list[str] | tuple[str, ...] = AUDIT_ATTACKS, echo: Callable[[str], None] = print,
              film: Callable[[Path, Path], Any] | None = None, victim: str = "") -> dict:
    """The audit (see the module); ``setup_for(target, epsilon, reward)`` makes each cell's setup and
    ``config_for(attack, target)`` its settings. ``film(run, video)``, if given, films the strongest attack of each
    target at its largest ε. Returns the audit's record (also ``<out>/audit.json``, ``audit.csv``)."""
    from rat.attacks.probe import steering_for

    attacks, epsilons = list(attacks), sorted(epsilons)
    check_audit(epsilons, budget_minutes, attacks)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    started, took, rows = time.perf_counter(), {}, []
    for attack in attacks:  # rounds: one attack at every target and ε before the next attack
        for target in targets:
            for epsilon in epsilons:
                directory = out / target / f"eps{epsilon:g}" / attack
                row = {"target": target, "epsilon": epsilon, "attack": attack,
                       "reward": measured_reward(get_attack(attack))}
                left = budget_minutes - (time.perf_counter() - started) / 60
                if (directory / "report.json").exists():
                    rows.append(row | _measured(AttackReport.read(directory), "done"))
                    continue
                if attack == "probe":
                    try:
                        steering_for(target)
                    except RatError as exc:
                        rows.append(row | {"status": "not applicable", "why": str(exc).split(";")[0]})
                        continue
                if left <= 0 or took.get(attack, 0.0) > left:
                    why = (f"the budget of {budget_minutes:g} minutes was spent" if left <= 0 else
                           f"{attack} took {took[attack]:.1f} minutes at a smaller ε; {left:.1f} were left")
                    rows.append(row | {"status": "not run", "why": why})
                    continue
                echo(f"{target}, ε = {epsilon:g}: {attack} ({left:.0f} of {budget_minutes:g} minutes left)")
                t0 = time.perf_counter()
                report = get_attack(attack).train(setup_for(target, epsilon, row["reward"]),
                                                  config_for(attack, target), directory)
                took[attack] = (time.perf_counter() - t0) / 60
                rows.append(row | _measured(report, "done") | {"minutes": round(took[attack], 2)})
    videos = _film(rows, out, film) if film is not None else {}
    record = {"victim": victim, "targets": targets, "epsilons": epsilons, "attacks": attacks, "budget_minutes": budget_minutes,
              "minutes": round((time.perf_counter() - started) / 60, 2), "rows": rows, "videos": videos}
    (out / "audit.json").write_text(json.dumps(record, indent=1))
    with open(out / "audit.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, FIELDS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    plot_audit(record, out / "audit.png")
    return record


def _measured(report: AttackReport, status: str) -> dict:
    return {"status": status, "attack_success_rate": report.attack_success_rate,
            "ci_low": report.attack_success_ci[0], "ci_high": report.attack_success_ci[1],
            "attacked_return": report.attacked_return, "clean_success_rate": report.clean_success_rate,
            "clean_return": report.clean_return, "max_perturbation": report.max_perturbation,
            "mean_perturbation": report.mean_perturbation, "episodes": report.episodes,
            "minutes": report.train_minutes}


def _film(rows: list[dict], out: Path, film: Callable[[Path, Path], Any]) -> dict[str, str]:
    """The strongest attack of each target at its largest measured ε, filmed."""
    videos = {}
    for target in sorted({r["target"] for r in rows}):
        done = [r for r in rows if r["target"] == target and r["status"] == "done"]
        if not done:
            continue
        top = max(done, key=lambda r: (r["epsilon"], r["attack_success_rate"]))
        name = f"{target}-eps{top['epsilon']:g}-{top['attack']}.mp4"
        if not (out / name).exists():
            film(out / target / f"eps{top['epsilon']:g}" / top["attack"], out / name)
        videos[target] = name
    return videos


def plot_audit(record: dict, path: Path) -> Path:
    """Target success and task return against ε, a line per attack, a column per target."""
    from rat.plots import pyplot

    plt = pyplot()
    targets = record["targets"]
    fig, axes = plt.subplots(2, len(targets), figsize=(5.5 * len(targets), 7), squeeze=False)
    for column, target in enumerate(targets):
        mine = [r for r in record["rows"] if r["target"] == target and r["status"] == "done"]
        for i, attack in enumerate(record["attacks"]):
            points = sorted((r["epsilon"], r) for r in mine if r["attack"] == attack)
            if not points:
                continue
            eps = [e for e, _ in points]
            axes[0][column].errorbar(eps, [100 * r["attack_success_rate"] for _, r in points],
                                     yerr=[[max(0.0, 100 * (r["attack_success_rate"] - r["ci_low"])) for _, r in points],
                                           [max(0.0, 100 * (r["ci_high"] - r["attack_success_rate"])) for _, r in points]],
                                     marker="o", capsize=3, color=f"C{i}", label=attack)
            if all(r["attacked_return"] is not None for _, r in points):
                axes[1][column].plot(eps, [r["attacked_return"] for _, r in points], marker="o", color=f"C{i}",
                                     label=attack)
        clean = [r["clean_return"] for r in mine if r["clean_return"] is not None]
        if clean:
            axes[1][column].axhline(clean[0], color="0.4", linestyle="--", label="clean")
        axes[0][column].set(title=f"target {target}", xlabel="ε", ylabel="target reached (%)", ylim=(-5, 105))
        axes[1][column].set(xlabel="ε", ylabel="task return")
        for ax in axes[:, column]:
            ax.grid(alpha=0.3)
            if ax.get_lines():
                ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
