"""The threat model, in one place: s̃ = s + ε·P(Δ), used in training, data collection and evaluation.

:class:`ThreatModel` is the budget (ε and its norm) as one value; :class:`AttackedObservation` shows
any gymnasium agent the attacked observation.

The adversary emits Δ ∈ (−1, 1)^d; P projects it onto the unit ball of the chosen norm, so
‖s̃ − s‖ ≤ ε always holds in that norm. ε is in raw observation units (for Meta-World, metres
and gripper units of the 39-d observation), and is reported with its norm.

Norms: ``linf`` (the paper's; P clips to [−1, 1]), ``l2`` (radial rescale), ``l1`` (Euclidean
projection onto the ℓ1 ball, Duchi et al. 2008), and ``l1-rescale`` (Δ / max(1, ‖Δ‖₁), what the
released code applied at deployment; reachable only by name).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch

from rat.errors import RatError

NORMS = ("linf", "l2", "l1", "l1-rescale")


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


Perturbation = Callable[[np.ndarray], np.ndarray]  # true observation -> Δ (before projection)


@dataclass(frozen=True)
class ThreatModel:
    """The attacker's budget: every attacked observation lies within ``epsilon`` of the true one in ``norm``.

    One value for every function that needs a budget, so training, data collection and
    evaluation cannot disagree on it.

    Attributes:
        epsilon: radius of the ball, in raw observation units (Meta-World: the 39-d observation).
        norm: ``linf`` (the paper's), ``l2``, ``l1`` or ``l1-rescale`` (see the module docstring).
    """

    epsilon: float = 0.1  #: radius of the ball, raw observation units
    norm: str = "linf"  #: linf (the paper's), l2, l1 or l1-rescale

    def __post_init__(self):
        if self.norm not in NORMS:
            raise RatError(f"unknown norm '{self.norm}'; use one of: {', '.join(NORMS)}")
        if not np.isfinite(self.epsilon) or self.epsilon < 0:
            raise RatError(f"the budget epsilon must be a finite number >= 0, got {self.epsilon}")
        object.__setattr__(self, "epsilon", float(self.epsilon))

    def project(self, delta: torch.Tensor) -> torch.Tensor:
        """Each row of ``delta [..., d]`` projected onto the unit ball of the norm."""
        return project(delta, self.norm)

    def perturb(self, obs: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        """The attacked observation s̃ = s + ε·P(Δ) (differentiable in Δ)."""
        return obs + self.epsilon * project(delta, self.norm)

    def size(self, diff: np.ndarray) -> np.ndarray:
        """‖diff‖ in the norm over the last axis (``l1-rescale`` is measured in ℓ1)."""
        return perturbation_norm(np.asarray(diff), self.norm)

    def contains(self, obs: np.ndarray, attacked: np.ndarray, tolerance: float = 1e-6) -> bool:
        """Whether every attacked observation lies in the ball around its true one."""
        return bool(np.all(self.size(np.asarray(attacked) - np.asarray(obs)) <= self.epsilon * (1 + tolerance) + 1e-12))

    def random_delta(self, rng: np.random.Generator, dim: int) -> np.ndarray:
        """A uniformly random point of the unit ball (the random attack's Δ)."""
        return random_delta(rng, dim, self.norm)

    def __str__(self) -> str:
        return f"epsilon {self.epsilon:g} ({self.norm}, raw observation units)"


class AttackedObservation(gym.ObservationWrapper):
    """Show the agent s̃ = s + ε·P(Δ(s)) while the environment's true state is untouched.

    ``info["true_obs"]`` carries the unperturbed observation, ``info["perturbation_norm"]`` the
    size of this step's perturbation; :attr:`norms` collects every one, and :attr:`records` each
    with its episode (counted from 0) and episode step (0 for the observation after a reset).

    Args:
        env: any gymnasium environment with a ``Box`` observation space.
        perturbation: maps a true observation to Δ (numpy); projected here. If it has ``reset()``
            (state kept within an episode), that is called at every reset; if it has ``observe(seen,
            action, reward)`` (one that follows a sequence victim's history), it is told each step
            taken — the observation as the agent saw it, the action, the reward — before it perturbs
            the next observation.
        threat: the budget.
    """

    def __init__(self, env: gym.Env, perturbation: Perturbation, threat: ThreatModel):
        super().__init__(env)
        self.perturbation, self.threat = perturbation, threat
        self.norms: list[float] = []
        self.records: list[tuple[int, int, float]] = []
        self._episode, self._t = -1, 0
        self._last_true: np.ndarray | None = None
        self._last_seen: np.ndarray | None = None

    def observation(self, obs: np.ndarray) -> np.ndarray:
        self._last_true = np.asarray(obs)
        delta = torch.as_tensor(self.perturbation(obs), dtype=torch.float64)
        attacked = self.threat.perturb(torch.as_tensor(obs, dtype=torch.float64), delta).numpy()
        self.norms.append(float(self.threat.size(attacked - obs)))
        self.records.append((self._episode, self._t, self.norms[-1]))
        self._last_seen = attacked.astype(np.asarray(obs).dtype)
        return self._last_seen

    def reset(self, **kwargs):
        self._episode, self._t = self._episode + 1, 0
        if hasattr(self.perturbation, "reset"):  # a perturbation that carries state within an episode
            self.perturbation.reset()
        obs, info = super().reset(**kwargs)
        info = dict(info, true_obs=self._last_true, perturbation_norm=self.norms[-1])
        return obs, info

    def step(self, action):
        self._t += 1
        obs, reward, terminated, truncated, info = self.env.step(action)
        if hasattr(self.perturbation, "observe"):  # the step just taken, before the next observation's Δ
            self.perturbation.observe(self._last_seen, action, reward)
        obs = self.observation(obs)
        info = dict(info, true_obs=self._last_true, perturbation_norm=self.norms[-1])
        return obs, reward, terminated, truncated, info
