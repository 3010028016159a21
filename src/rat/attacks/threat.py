"""The threat model, in one place: s̃ = s + ε·P(Δ), used in training, data collection and evaluation.

The adversary emits Δ ∈ (−1, 1)^d; P projects it onto the unit ball of the chosen norm, so
‖s̃ − s‖ ≤ ε always holds in that norm. ε is in raw observation units (for Meta-World, metres
and gripper units of the 39-d observation), and is reported with its norm.

Norms: ``linf`` (the paper's; P clips to [−1, 1]), ``l2`` (radial rescale), ``l1`` (Euclidean
projection onto the ℓ1 ball, Duchi et al. 2008), and ``l1-rescale`` (Δ / max(1, ‖Δ‖₁), what the
released code applied at deployment; reachable only by name).
"""

from __future__ import annotations

from typing import Callable

import gymnasium as gym
import numpy as np
import torch

from rat.errors import RatError

NORMS = ("linf", "l2", "l1", "l1-rescale")


def check_budget(epsilon: float, norm: str) -> None:
    if norm not in NORMS:
        raise RatError(f"unknown norm '{norm}'; use one of: {', '.join(NORMS)}")
    if not np.isfinite(epsilon) or epsilon < 0:
        raise RatError(f"the budget epsilon must be a finite number >= 0, got {epsilon}")


def _project_l1(delta: torch.Tensor) -> torch.Tensor:
    """Euclidean projection of each row onto the unit ℓ1 ball (sort-based, exact)."""
    abs_d = delta.abs()
    inside = abs_d.sum(-1, keepdim=True) <= 1.0
    mu, _ = torch.sort(abs_d, dim=-1, descending=True)
    cumsum = mu.cumsum(-1)
    k = torch.arange(1, delta.shape[-1] + 1, device=delta.device, dtype=delta.dtype)
    cond = mu - (cumsum - 1.0) / k > 0
    rho = cond.to(delta.dtype).cumsum(-1).argmax(-1, keepdim=True)  # last index where cond holds
    theta = (cumsum.gather(-1, rho) - 1.0) / (rho + 1).to(delta.dtype)
    projected = torch.sign(delta) * torch.clamp(abs_d - theta, min=0.0)
    return torch.where(inside, delta, projected)


def project(delta: torch.Tensor, norm: str = "linf") -> torch.Tensor:
    """Project each row of ``delta [..., d]`` onto the unit ball of ``norm``."""
    if norm == "linf":
        return delta.clamp(-1.0, 1.0)
    if norm == "l2":
        n = delta.norm(dim=-1, keepdim=True)
        return delta / torch.clamp(n, min=1.0)
    if norm == "l1":
        return _project_l1(delta)
    if norm == "l1-rescale":
        return delta / torch.clamp(delta.abs().sum(-1, keepdim=True), min=1.0)
    raise RatError(f"unknown norm '{norm}'; use one of: {', '.join(NORMS)}")


def perturb(obs: torch.Tensor, delta: torch.Tensor, epsilon: float, norm: str = "linf") -> torch.Tensor:
    """The attacked observation s̃ = s + ε·P(Δ) (differentiable in Δ)."""
    return obs + epsilon * project(delta, norm)


def perturbation_norm(diff: np.ndarray, norm: str) -> np.ndarray:
    """‖diff‖ in ``norm`` over the last axis (``l1-rescale`` is measured in ℓ1)."""
    order = {"linf": np.inf, "l2": 2, "l1": 1, "l1-rescale": 1}[norm]
    return np.linalg.norm(diff, ord=order, axis=-1)


def random_delta(rng: np.random.Generator, dim: int, norm: str) -> np.ndarray:
    """A uniformly random point of the unit ball of ``norm`` (the random attack)."""
    if norm == "linf":
        return rng.uniform(-1.0, 1.0, dim)
    direction = rng.standard_normal(dim) if norm == "l2" else rng.laplace(size=dim)
    p = 2 if norm == "l2" else 1
    direction /= np.linalg.norm(direction, ord=p)
    return direction * rng.uniform() ** (1.0 / dim)  # radius for a uniform density in the ball


Adversary = Callable[[np.ndarray], np.ndarray]  # true observation -> Δ (before projection)


class AttackedObservation(gym.ObservationWrapper):
    """Show the agent s̃ = s + ε·P(Δ(s)) while the environment's true state is untouched.

    ``info["true_obs"]`` carries the unperturbed observation, ``info["perturbation_norm"]`` the
    size of this step's perturbation in ``norm``; :attr:`norms` collects every one.

    Args:
        env: any gymnasium environment with a ``Box`` observation space.
        adversary: maps a true observation to Δ (numpy); projected here.
        epsilon, norm: the budget.
    """

    def __init__(self, env: gym.Env, adversary: Adversary, epsilon: float, norm: str = "linf"):
        super().__init__(env)
        check_budget(epsilon, norm)
        self.adversary, self.epsilon, self.norm = adversary, float(epsilon), norm
        self.norms: list[float] = []
        self._last_true: np.ndarray | None = None

    def observation(self, obs: np.ndarray) -> np.ndarray:
        self._last_true = np.asarray(obs)
        delta = torch.as_tensor(self.adversary(obs), dtype=torch.float64)
        attacked = perturb(torch.as_tensor(obs, dtype=torch.float64), delta, self.epsilon, self.norm).numpy()
        self.norms.append(float(perturbation_norm(attacked - obs, self.norm)))
        return attacked.astype(np.asarray(obs).dtype)

    def reset(self, **kwargs):
        obs, info = super().reset(**kwargs)
        info = dict(info, true_obs=self._last_true, perturbation_norm=self.norms[-1])
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = super().step(action)
        info = dict(info, true_obs=self._last_true, perturbation_norm=self.norms[-1])
        return obs, reward, terminated, truncated, info
