"""Attacks on victims this project did not make: random, the white-box probe and RAT on each foreign victim of
``benchmarks/foreign_victims.py``, several seeds, and the table that says whether RAT beats random where the probe
shows the victim can be steered, and how far it stays below the probe.

Each (victim, seed) is one ``rat audit`` (target ``reach``, ε = 0.1, attacks ``random,probe,rat``, the ``cpu``
preset) in ``<out>/<victim>/seed<k>``, resumable like any audit; the table pools each attack's episodes over the
seeds:

- *probe steers*: the probe reaches the target in more episodes than the clean agent (Fisher, one-sided, p < 0.05);
- *RAT > random*: Fisher one-sided on the pooled episodes, p < 0.05;
- *the goal* (where the probe steers): RAT > random and RAT within 20 points of the probe's success.

    OMP_NUM_THREADS=1 python benchmarks/foreign_attacks.py --victims benchmarks/foreign --seeds 0,1,2
    python benchmarks/foreign_attacks.py --victims benchmarks/foreign --table-only      # the table from what ran

The table is written to ``<out>/table.md`` and ``<out>/table.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

ATTACKS = ("random", "probe", "rat")
TARGET, EPSILON = "reach", 0.1
WITHIN = 0.20  #: the goal: RAT's success within this of the probe's


def audit_command(victim_file: Path, task: str, seed: int, out: Path, budget_minutes: float) -> list[str]:
    """The ``rat audit`` arguments of one (victim, seed)."""
    return ["audit", str(victim_file), "--task", task, "--targets", TARGET, "--epsilons", f"{EPSILON:g}",
            "--attacks", ",".join(ATTACKS), "--seed", str(seed), "--budget-minutes", f"{budget_minutes:g}",
            "--no-video", "--out", str(out)]


def pooled(audits: list[dict]) -> dict[str, dict]:
    """Per attack (and the clean agent), the target's hits and episodes summed over ``audits`` at (TARGET, EPSILON)."""
    counts: dict[str, dict] = {}

    def add(name: str, rate: float, n: int) -> None:
        c = counts.setdefault(name, {"hits": 0, "episodes": 0, "seeds": 0})
        c["hits"], c["episodes"], c["seeds"] = c["hits"] + round(rate * n), c["episodes"] + n, c["seeds"] + 1

    for audit in audits:
        for row in audit["rows"]:
            if row["status"] != "done" or row["target"] != TARGET or abs(row["epsilon"] - EPSILON) > 1e-12:
                continue
            add(row["attack"], row["attack_success_rate"], int(row["episodes"]))
            if row["attack"] == "random":  # the clean agent once per audit: beside the random attack's episodes
                add("clean", row["clean_success_rate"], int(row["episodes"]))
    return counts


def greater(a: dict, b: dict) -> float:
    """Fisher's one-sided p that ``a`` reaches the target more often than ``b``."""
    from scipy import stats

    table = [[a["hits"], a["episodes"] - a["hits"]], [b["hits"], b["episodes"] - b["hits"]]]
    return float(stats.fisher_exact(table, alternative="greater").pvalue)


def summarise(victim: str, record: dict, audits: list[dict]) -> dict:
    """One line of the table for ``victim`` (``record``: its entry of victims.json)."""
    c = pooled(audits)
    rate = {name: c[name]["hits"] / c[name]["episodes"] for name in c}
    line = {"victim": victim, "algorithm": record.get("algorithm"), "held_out": bool(record.get("held_out")),
            "seeds": min((c[a]["seeds"] for a in ATTACKS if a in c), default=0), **{f"{k}_success": v for k, v in rate.items()}}
    if not all(a in c for a in (*ATTACKS, "clean")):
        return line | {"complete": False}
    steers = greater(c["probe"], c["clean"]) < 0.05
    p = greater(c["rat"], c["random"])
    gap = rate["probe"] - rate["rat"]
    return line | {"complete": True, "probe_steers": steers, "rat_vs_random_p": p, "probe_minus_rat": gap,
                   "goal_met": (p < 0.05 and gap <= WITHIN) if steers else None}


def table_markdown(lines: list[dict]) -> str:
    head = ("| victim | algorithm | seeds | clean | random | probe | RAT | RAT > random (p) | probe − RAT | goal |\n"
            "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |\n")
    pct = lambda x: "–" if x is None else f"{100 * x:.0f}%"  # noqa: E731
    rows = []
    for x in lines:
        name = x["victim"] + (" (held out)" if x["held_out"] else "")
        if not x.get("complete"):
            rows.append(f"| {name} | {x['algorithm']} | {x['seeds']} | not finished |||||||")
            continue
        goal = "probe cannot steer" if x["goal_met"] is None else ("met" if x["goal_met"] else "**not met**")
        rows.append(f"| {name} | {x['algorithm']} | {x['seeds']} | {pct(x['clean_success'])} | "
                    f"{pct(x['random_success'])} | {pct(x['probe_success'])} | {pct(x['rat_success'])} | "
                    f"{x['rat_vs_random_p']:.2g} | {100 * x['probe_minus_rat']:+.0f} | {goal} |")
    return head + "\n".join(rows) + "\n"


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--victims", type=Path, default=Path("benchmarks/foreign"), help="foreign_victims.py's --out")
    parser.add_argument("--out", type=Path, default=None, help="default: <victims>/attacks")
    parser.add_argument("--only", default="", help="comma-separated victim names (default: all in victims.json)")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--budget-minutes", type=float, default=600.0, help="of each audit")
    parser.add_argument("--table-only", action="store_true", help="run nothing; the table from the audits there")
    args = parser.parse_args(argv)
    out = args.out or args.victims / "attacks"
    records = json.loads((args.victims / "victims.json").read_text())
    chosen = [name for name in records if not args.only or name in args.only.split(",")]
    seeds = [int(s) for s in args.seeds.split(",")]
    if not args.table_only:
        from rat.cli import main as rat

        for seed in seeds:  # every victim at one seed before the next seed: a short session still covers them all
            for name in chosen:
                record = records[name]
                code = rat(audit_command(args.victims / record["file"], record["task"], seed, out / name / f"seed{seed}",
                                         args.budget_minutes))
                if code:
                    raise SystemExit(code)
    lines = []
    for name in chosen:
        audits = [json.loads(p.read_text()) for p in sorted((out / name).glob("seed*/audit.json"))]
        lines.append(summarise(name, records[name], audits))
    out.mkdir(parents=True, exist_ok=True)
    (out / "table.json").write_text(json.dumps(lines, indent=1) + "\n")
    (out / "table.md").write_text(table_markdown(lines))
    print(table_markdown(lines))
    return lines


if __name__ == "__main__":
    main()
