"""Figures people would rather see than read: training curves and learned-vs-true rewards."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np


def pyplot():
    """matplotlib's pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_reward_quality(episode: dict[str, np.ndarray], r_hat: np.ndarray, path: Path, title: str) -> Path:
    """Standardised learned vs true reward along one rollout."""
    plt = pyplot()

    def z(x):
        return (x - x.mean()) / (x.std() + 1e-8)

    fig, ax = plt.subplots(figsize=(7, 3.2))
    ax.plot(z(r_hat), label="learned reward r̂ (standardised)", color="tab:blue")
    ax.plot(z(episode["reward"]), label="true target reward (standardised)", color="tab:orange", alpha=0.8)
    ax.set_xlabel("episode step")
    ax.set_title(title)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _logged_rows(metrics_csv: Path, key: str) -> list[dict[str, str]]:
    """The rows of a run's metrics.csv that logged ``key`` (none where nothing was logged)."""
    if not Path(metrics_csv).exists():
        return []
    with open(metrics_csv, newline="") as f:
        return [r for r in csv.DictReader(f) if r.get(key)]


def plot_training(metrics_csv: Path, path: Path, title: str, curve: str = "evaluations during training",
                  final: tuple[float, float, str] | None = None) -> Path | None:
    """Evaluation success over environment steps, from a run's metrics.csv.

    ``final`` = (step, success rate, label) marks the result as deployed at the end of a run, where that is not
    what the evaluations during training measured (a RAT attack refines Δ at every observation; they do not).
    """
    rows = _logged_rows(metrics_csv, "eval_success_rate")
    if not rows:
        return None
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.2))
    ax.plot([float(r["step"]) for r in rows], [100 * float(r["eval_success_rate"]) for r in rows], marker="o",
            label=curve)
    if final is not None:
        step, rate, label = final
        ax.plot([step], [100 * rate], marker="*", markersize=14, linestyle="none", color="tab:red", label=label)
        ax.legend(loc="best", fontsize=8)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("target success (%)")
    ax.set_ylim(-3, 103)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120, metadata={"Title": title.replace("\n", " ")})  # the words, for a reader of the file
    plt.close(fig)
    return path


def plot_robust_training(metrics_csv: Path, path: Path, title: str) -> Path | None:
    """A robust agent's task return over training, clean and under its adversary, from a run's metrics.csv."""
    rows = _logged_rows(metrics_csv, "eval_clean_return")
    if not rows:
        return None
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.2))
    for key, label in (("eval_clean_return", "clean"), ("eval_attacked_return", "under its adversary")):
        points = [(float(r["step"]), float(r[key])) for r in rows if r.get(key)]
        if points:
            ax.plot(*zip(*points), marker="o", label=label)
    ax.set_xlabel("environment steps (agent and adversary)")
    ax.set_ylabel("episode task return")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120, metadata={"Title": title.replace("\n", " ")})
    plt.close(fig)
    return path
