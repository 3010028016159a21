"""Evaluation: success rate with a confidence interval, returns, and videos of episodes."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy import stats
from tqdm.auto import tqdm

from rat.envs.targets import TargetBehaviour

Policy = Callable[[np.ndarray], np.ndarray]


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (well-behaved at 0% and 100%)."""
    if n == 0:
        return 0.0, 1.0
    z = stats.norm.ppf(0.5 + confidence / 2)
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


@dataclass
class EvalResult:
    """Outcome of N evaluation episodes. Success means the success test held at *any* step."""

    episodes: int
    success_rate: float
    success_ci: tuple[float, float]  # 95% Wilson interval
    mean_return: float  # of the environment's own reward
    std_return: float
    successes: list[bool] = field(default_factory=list)
    first_success_step: list[int] = field(default_factory=list)  # -1 where never
    success_at_last_step: float = 0.0  # share of episodes whose final step passes the test

    def summary(self, with_success: bool = True) -> str:
        """One line; ``with_success=False`` for tasks that only have a return (locomotion's own task)."""
        if not with_success:
            return f"return {self.mean_return:.1f} +- {self.std_return:.1f} over {self.episodes} episodes"
        lo, hi = self.success_ci
        return (f"success {100 * self.success_rate:.1f}% (95% CI {100 * lo:.1f}-{100 * hi:.1f}%, "
                f"{sum(self.successes)}/{self.episodes} episodes, any step); "
                f"return {self.mean_return:.1f} +- {self.std_return:.1f}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def of(cls, returns: Sequence[float], first_success_step: Sequence[int], success_at_last: Sequence[bool]) -> EvalResult:
        """The outcome of episodes given, per episode, its return, its first successful step (-1: none) and
        whether its last step passed the test."""
        successes = [step >= 0 for step in first_success_step]
        n_ok, episodes = sum(successes), len(successes)
        return cls(episodes=episodes, success_rate=n_ok / episodes, success_ci=wilson_interval(n_ok, episodes),
                   mean_return=float(np.mean(returns)), std_return=float(np.std(returns)), successes=successes,
                   first_success_step=list(first_success_step), success_at_last_step=float(np.mean(success_at_last)))


def write_video(frames: list[np.ndarray], path: str | Path, fps: int = 30) -> Path:
    """Write RGB frames to an mp4 (or gif, by suffix)."""
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".gif":
        imageio.mimsave(path, frames, duration=1000 / fps, loop=0)
    else:
        imageio.mimsave(path, frames, fps=fps, macro_block_size=1)
    return path


def evaluate(policy: Policy, env, episodes: int, seed: int, target: TargetBehaviour | None = None,
             video: str | Path | None = None, video_episodes: int | Sequence[int] = 2, video_every: int = 2,
             progress: bool = False, stop_at_success: bool = False, desc: str = "evaluating") -> EvalResult:
    """Run ``policy`` for ``episodes`` episodes of ``env``.

    Args:
        policy: observation -> action (numpy); if it has ``reset()`` and ``observe(reward)`` (a
            :class:`~rat.victims.base.VictimPolicy` of a sequence victim), they are called at each
            episode's start and after each step.
        env: a gymnasium environment whose ``info`` carries what ``target.success`` reads.
        seed: episode ``i`` is reset with ``seed + i``, so two evaluations see the same episodes.
        target: the success test (and nothing else) is taken from it; default: ``info["success"]``.
        video: if given, the first ``video_episodes`` episodes (or those with these indices) are recorded there (needs
            ``render_mode="rgb_array"``), one frame every ``video_every`` steps.
        stop_at_success: end an episode at its first success (faster; returns are then partial).
        progress, desc: show a progress bar over the episodes, and its label.
    """
    filmed = set(range(video_episodes)) if isinstance(video_episodes, int) else set(video_episodes)
    returns, first, last = [], [], []
    frames: list[np.ndarray] = []
    for ep in tqdm(range(episodes), desc=desc, disable=not progress, leave=False):
        obs, info = env.reset(seed=seed + ep)
        if hasattr(policy, "reset"):
            policy.reset()
        success_fn = target.episode_success() if target is not None else (lambda info: bool(info["success"]))
        total, first_step, t, done = 0.0, -1, 0, False
        ok_now = False
        while not done:
            if video is not None and ep in filmed and t % video_every == 0:
                frames.append(env.render())
            obs, reward, terminated, truncated, info = env.step(policy(obs))
            if hasattr(policy, "observe"):
                policy.observe(reward)
            total += reward
            ok_now = success_fn(info)
            if ok_now and first_step < 0:
                first_step = t
            t += 1
            done = terminated or truncated or (stop_at_success and first_step >= 0)
        returns.append(total)
        first.append(first_step)
        last.append(ok_now)
    if video is not None and frames:
        write_video(frames, video)
    return EvalResult.of(returns, first, last)
