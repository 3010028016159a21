"""Markdown rows from finished run directories (report.json + metrics.csv), for benchmarks/*.md.

    python benchmarks/summarize.py intention RUN_DIR...   # `rat intention train` runs
    python benchmarks/summarize.py attack RUN_DIR...      # `rat attack train` runs
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path


def curve(run: Path) -> str:
    """Evaluation success over environment steps, as 'step: %' pairs."""
    with open(run / "metrics.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if r.get("eval_success_rate")]
    return ", ".join(f"{int(float(r['step'])) // 1000}k: {100 * float(r['eval_success_rate']):.0f}%" for r in rows)


def intention(runs: list[Path]) -> None:
    print("| target | environment | labels | steps | target success (30 ep.) | 95% CI | preference accuracy "
          "(held out) | Pearson r̂ vs true | minutes | success during training (10 ep.) |")
    print("| --- | --- | ---: | ---: | ---: | --- | ---: | ---: | ---: | --- |")
    for run in runs:
        r = json.loads((run / "report.json").read_text())
        lo, hi = r["target_success_ci"]
        print(f"| {r['target']} | {r['task']} | {r['labels']} | {r['steps']:,} | {100 * r['target_success_rate']:.1f}% | "
              f"{100 * lo:.0f}–{100 * hi:.0f}% | {100 * r['preference_accuracy']:.1f}% | {r['reward_pearson']:.2f} | "
              f"{r['train_minutes_this_session']:.0f} | {curve(run)} |")


def attack(runs: list[Path]) -> None:
    print("| victim | target | environment | ε (norm) | labels | steps | attack success (30 ep.) | 95% CI | "
          "max ‖s̃−s‖ | minutes | success during training (10 ep.) |")
    print("| --- | --- | --- | --- | ---: | ---: | ---: | --- | ---: | ---: | --- |")
    for run in runs:
        r = json.loads((run / "report.json").read_text())
        lo, hi = r["attack_success_ci"]
        print(f"| {r['victim']} | {r['target']} | {r['task']} | {r['epsilon']} ({r['norm']}) | {r['labels']} | "
              f"{r['steps']:,} | {100 * r['attack_success_rate']:.1f}% | {100 * lo:.0f}–{100 * hi:.0f}% | "
              f"{r['max_perturbation']:.4f} | {r['train_minutes_this_session']:.0f} | {curve(run)} |")


if __name__ == "__main__":
    kind, *dirs = sys.argv[1:]
    {"intention": intention, "attack": attack}[kind]([Path(d) for d in dirs])
