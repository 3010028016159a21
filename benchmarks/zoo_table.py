"""Render the victim-zoo timings recorded by `rat victim zoo` as the markdown table in benchmarks/zoo.md.

    python benchmarks/zoo_table.py > benchmarks/zoo.md
"""

import json

from rat.victims.zoo import ZOO_DIR

rows = json.loads((ZOO_DIR / "timings.json").read_text())
meta = {t: json.loads((ZOO_DIR / f"{t}.json").read_text())["meta"] for t in rows}
commits = sorted({m["commit"] for m in meta.values()})
print("# Victim-zoo generation\n")
print("Behaviour clones (`bc`): made by `rat victim zoo --jobs 2` (behaviour cloning of the scripted expert with")
print("DART noise σ = 0.3: 100 demonstrations of 200 steps, 20,000 updates of a 3×256 tanh-Gaussian actor,")
print("batch 256), two tasks at a time on this project's 2-core CPU machine, torch pinned to one thread per process.")
print("SAC victims (`sac-demo`, shipped as `<task>@sac`): SAC's own actor trained by SAC's losses at the paper's")
print("table-7 settings (3×256, lr 1e-4, batch 1,024, initial temperature 0.1), its replay buffer seeded with 100")
print("noisy scripted demonstrations and no behaviour cloning, evaluated every 10,000 steps, stopped after three")
print("evaluations in a row at 100% and kept at its best evaluation:")
print("`rat victim train --task <task> --method sac-demo --set bc_updates=0 --total-steps 300000 --set stop_success=1.0`")
print("`--set keep=best --set checkpoint_every=5000`, resumed across sessions.")
print(f"Code commit(s): {', '.join(commits)}. Clean success is over 50 evaluation episodes that training never")
print("saw, counted as success at any step; the last-step column is the share that still pass at step 500.\n")
print("| task | method | minutes | clean success (50 ep.) | 95% CI | success at last step | mean return |")
print("| --- | --- | ---: | ---: | --- | ---: | ---: |")
for task, r in sorted(rows.items()):
    lo, hi = r["success_ci"]
    print(f"| {task} | {r['method']} | {r['minutes']:.1f} | {100 * r['clean_success']:.0f}% | "
          f"{100 * lo:.1f}–{100 * hi:.1f}% | {100 * r['success_at_last_step']:.0f}% | {r['mean_return']:.0f} |")
total = sum(r["minutes"] for r in rows.values() if r["method"] == "bc")
print(f"\nSum of the behaviour clones' minutes: {total:.1f} (wall clock is about half with two processes).")
for task, r in sorted(rows.items()):
    if r["method"] != "bc":
        print(f"{task}: {r.get('env_steps', '?')} environment steps; {r.get('note', '')}.")
