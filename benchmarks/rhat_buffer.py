"""How close a finished RAT run's learned reward is to the true one, over its replay buffer, for the `reach`
target (the manipulation scenario): the buffer holds r̂ as the run last relabelled it, and the true reach
reward is recomputed from the gripper's positions in each transition's observations (the observation's first
three entries; the target's own reward reads the tool centre point, a few centimetres away on the same rigid
hand — ``--check`` measures how well the two agree on fresh steps of the run's task).

    python benchmarks/rhat_buffer.py RUN_DIR [RUN_DIR ...] [--check]

Per run: r̂'s per-step correlation with the true reward over three spans of the buffer, the correlation of
50-step segment returns, and how often random pairs of those segments are ordered as the true reward orders
them. Results are recorded in ``docs/notes/strength-log.md``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from safetensors import safe_open

from rat.envs.targets import REACH_GOAL, REACH_RADIUS
from rat.preferences.reward_model import reward_agreement

SPANS = ((0, 10_000), (10_000, 30_000), (30_000, 50_000))
SEGMENT = 50


def reach_reward(obs: np.ndarray, next_obs: np.ndarray, initial_distance: float = 0.3) -> np.ndarray:
    """The reach reward (``rat.envs.targets.reach_reward``) from gripper positions, batched: 10 × progress,
    plus the long-tail tolerance bonus within 0.1 m (its margin, the episode's first distance, taken as
    ``initial_distance``)."""
    before = np.linalg.norm(obs[:, :3] - REACH_GOAL, axis=1)
    after = np.linalg.norm(next_obs[:, :3] - REACH_GOAL, axis=1)
    x = np.maximum(after - REACH_RADIUS, 0.0) / initial_distance
    return 10.0 * (before - after) + (after < 0.1) / (x * x * 9.0 + 1.0)


def buffer_scores(run: Path) -> str:
    tensors = safe_open(str(run / "checkpoint.safetensors"), "np")
    obs, next_obs, r_hat = (tensors.get_tensor(f"state/learner/buffer/{k}") for k in ("obs", "next_obs", "reward"))
    r_hat, true = r_hat.reshape(-1), reach_reward(obs, next_obs)
    n = len(r_hat)
    parts = [f"{run.name} ({n} transitions)"]
    for lo, hi in SPANS:
        if lo < n:
            span = slice(lo, min(hi, n))
            step_corr = reward_agreement(r_hat[span], true[span], SEGMENT)["step_corr"]
            parts.append(f"per step {lo // 1000}k–{hi // 1000}k: {step_corr:.2f}")
    scores = reward_agreement(r_hat, true, SEGMENT)
    parts.append(f"segment returns: {scores['segment_corr']:.2f}")
    parts.append(f"random pairs ordered right: {scores['pairs_ordered']:.3f}")
    return " | ".join(parts)


def check(task: str, steps: int = 1500) -> float:
    """Correlation of :func:`reach_reward` with the target's own reward on ``steps`` goal-ward and random steps."""
    from rat.envs import make_task
    from rat.envs.targets import get_target

    env, target, rng = make_task(task, seed=1), get_target("reach"), np.random.default_rng(0)
    obs, _ = env.reset(seed=3)
    ours, theirs = [], []
    for k in range(steps):
        action = rng.uniform(-1, 1, env.action_space.shape)
        if k % 3:  # mostly towards the goal, so the tolerance bonus is reached too
            action[:3] = np.clip((REACH_GOAL - obs[:3]) * 10 + rng.normal(0, 0.5, 3), -1, 1)
        next_obs, _, terminated, truncated, info = env.step(action)
        theirs.append(target.reward(obs, action, next_obs, info))
        ours.append(reach_reward(obs[None], next_obs[None])[0])
        obs = next_obs
        if terminated or truncated:
            obs, _ = env.reset()
    return float(np.corrcoef(ours, theirs)[0, 1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+", help="RAT run directories (target reach)")
    parser.add_argument("--check", action="store_true", help="first, compare the recomputed reward with the target's")
    args = parser.parse_args()
    reports = {}
    for run in args.runs:
        if not (run / "report.json").is_file():
            parser.error(f"'{run}' holds no report.json: give a finished RAT run (or finish it by re-running its command)")
        reports[run] = json.loads((run / "report.json").read_text())
        if reports[run].get("target") != "reach":
            parser.error(f"'{run}' attacks for target '{reports[run].get('target')}'; this script recomputes the reach "
                         "reward only")
    if args.check:
        task = reports[args.runs[0]]["task"]
        print(f"recomputed vs the target's own reach reward on {task}: r = {check(task):.3f}")
    for run in args.runs:
        print(buffer_scores(run))


if __name__ == "__main__":
    main()
