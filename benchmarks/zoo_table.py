"""Render the victim-zoo timings recorded by `rat victim zoo` as the markdown table in benchmarks/zoo.md.

    python benchmarks/zoo_table.py > benchmarks/zoo.md
"""

import json

from rat.victims.zoo import ZOO_DIR

rows = json.loads((ZOO_DIR / "timings.json").read_text())
meta = {t: json.loads((ZOO_DIR / f"{t}.json").read_text())["meta"] for t in rows}
commits = sorted({m["commit"] for m in meta.values()})
print("# Victim-zoo generation\n")
print("Made by `rat victim zoo --jobs 2` (behaviour cloning of the scripted expert with DART noise σ = 0.3:")
print("100 demonstrations of 200 steps, 20,000 updates of a 3×256 tanh-Gaussian actor, batch 256),")
print("two tasks at a time on this project's 2-core CPU machine, torch pinned to one thread per process.")
print(f"Code commit(s): {', '.join(commits)}. Clean success is over 50 evaluation episodes that training never")
print("saw, counted as success at any step; the last-step column is the share that still pass at step 500.\n")
print("| task | method | minutes | clean success (50 ep.) | 95% CI | success at last step | mean return |")
print("| --- | --- | ---: | ---: | --- | ---: | ---: |")
for task, r in sorted(rows.items()):
    lo, hi = r["success_ci"]
    print(f"| {task} | {r['method']} | {r['minutes']:.1f} | {100 * r['clean_success']:.0f}% | "
          f"{100 * lo:.1f}–{100 * hi:.1f}% | {100 * r['success_at_last_step']:.0f}% | {r['mean_return']:.0f} |")
total = sum(r["minutes"] for r in rows.values())
print(f"\nSum of per-task minutes: {total:.1f} (wall clock is about half with two processes).")
