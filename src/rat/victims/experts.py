"""Meta-World's scripted expert policies, and demonstrations collected from them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm.auto import tqdm

from rat.envs.metaworld import MetaWorldTask
from rat.errors import RatError


def expert_for(task: str):
    """The scripted expert of a Meta-World v3 task (``metaworld.policies``)."""
    import metaworld.policies as policies

    camel = "".join(part.capitalize() for part in task.removesuffix("-v3").split("-"))
    name = f"Sawyer{camel}V3Policy"
    if not hasattr(policies, name):
        raise RatError(f"Meta-World has no scripted expert '{name}' for task '{task}'; "
                       "use --method sac, which needs no demonstrations")
    return getattr(policies, name)()


@dataclass
class Demonstrations:
    """Transitions from an expert, with its clean action as the label of every visited state."""

    obs: np.ndarray  # [N, obs_dim]
    action: np.ndarray  # [N, act_dim]: the expert's action at obs (the label)
    executed: np.ndarray  # [N, act_dim]: the action actually executed (label + noise, clipped)
    reward: np.ndarray  # [N]
    next_obs: np.ndarray  # [N, obs_dim]
    terminated: np.ndarray  # [N]
    success_rate: float  # share of episodes that succeeded at any step


def collect_demonstrations(env: MetaWorldTask, episodes: int, noise: float, rng: np.random.Generator,
                           episode_steps: int | None = None, progress: bool = False) -> Demonstrations:
    """Roll out the task's scripted expert with Gaussian action noise (DART).

    The executed action is the expert's plus ``N(0, noise^2)``; the stored label is the expert's
    clean action. States off the expert's own path are therefore labelled with the corrective
    action, which is what makes behaviour cloning robust to its own small errors.
    """
    expert = expert_for(env.task)
    rows: dict[str, list] = {k: [] for k in ("obs", "action", "executed", "reward", "next_obs", "terminated")}
    successes = 0
    for _ in tqdm(range(episodes), desc=f"demonstrations {env.task}", disable=not progress, leave=False):
        obs, _ = env.reset(seed=int(rng.integers(2**31)))
        success = False
        for _t in range(episode_steps or 10**9):
            label = np.clip(expert.get_action(obs), -1.0, 1.0)
            executed = np.clip(label + noise * rng.standard_normal(label.shape), -1.0, 1.0)
            next_obs, reward, terminated, truncated, info = env.step(executed)
            for key, value in zip(rows, (obs, label, executed, reward, next_obs, terminated)):
                rows[key].append(value)
            success |= info["success"]
            obs = next_obs
            if terminated or truncated:
                break
        successes += success
    arrays = {k: np.asarray(v, np.float32) for k, v in rows.items()}
    return Demonstrations(**arrays, success_rate=successes / episodes)
