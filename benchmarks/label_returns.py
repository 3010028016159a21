"""What the labelled segments of a run held, round by round, in the target's true reward.

    python benchmarks/label_returns.py RUN [--high 9]

Reads the run's label store (``RUN/labels.sqlite``; the true target reward of every step of every
labelled segment is stored beside it) and prints, for each query round: the pairs labelled, the largest
reward of a single step, the share of segments with a step at or above ``--high`` (on Meta-World, a step
inside the success region scores 10), and the 50th and 90th percentiles and the maximum of the segments'
returns. It tells whether the teacher was shown the behaviour at all, and whether late rounds still show it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from rat.errors import RatError
from rat.preferences.store import LabelStore


def round_summaries(store: LabelStore, high: float) -> list[dict]:
    """One row per query round of each source of the store's labels (a run's own, or imported), with its step."""
    labels = store.read()
    at = {(source, r["round"]): r["step"] for source, _ in store.sources() for r in store.rounds(source)}
    keys = [(row["source"], -1 if row["round"] is None else row["round"]) for row in labels.rows]
    steps = np.concatenate([labels.pairs.reward0, labels.pairs.reward1])  # [2n, L]: both segments of every pair
    out = []
    for source, r in sorted(set(keys)):
        pair = np.asarray([key == (source, r) for key in keys])
        x = steps[np.concatenate([pair, pair])]
        returns = x.sum(1)
        p50, p90 = np.percentile(returns, [50, 90])
        out.append({"source": source, "round": r, "step": at.get((source, r)), "pairs": len(x) // 2,
                    "max_step": float(x.max()),
                    "share_high": float((x.max(1) >= high).mean()), "return_p50": float(p50),
                    "return_p90": float(p90), "return_max": float(returns.max())})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", type=Path, help="a run directory with a labels.sqlite")
    parser.add_argument("--high", type=float, default=9.0, help="a step reward that marks the behaviour")
    args = parser.parse_args()
    try:
        with LabelStore(args.run / "labels.sqlite", read_only=True) as store:
            rows = round_summaries(store, args.high)
    except RatError as exc:
        parser.error(str(exc))
    several = len({row["source"] for row in rows}) > 1
    print(f"| {'source / ' if several else ''}round | step | pairs | largest step reward | segments with a step ≥ {args.high:g} | return p50 | p90 | max |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for row in rows:
        name = f"{row['source']} / {row['round']}" if several else row["round"]
        print(f"| {name} | {row['step'] or '?'} | {row['pairs']} | {row['max_step']:.2f} | {row['share_high']:.2f} | "
              f"{row['return_p50']:.0f} | {row['return_p90']:.0f} | {row['return_max']:.0f} |")


if __name__ == "__main__":
    main()
