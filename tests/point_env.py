"""A small, fast environment shipped with the tests: a point that a victim steers to a goal.

Observation (4): point x, y and goal x, y. Action (2): velocity, 0.05 per step at most. Episodes
last 40 steps. The victim heads for the goal it *observes*; the target behaviour (``beside``) is
to reach 0.15 to the right of the true goal, past where the victim stops, which an attacker can only bring about by shifting
what the victim sees, consistently, in one direction.
"""

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from rat.envs.targets import TargetBehaviour
from rat.victims import ModuleVictim

OFFSET = np.array([0.15, 0.0])
HORIZON = 40


class PointGoal(gym.Env):
    def __init__(self, seed: int = 0):
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (4,), np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.spec = gym.envs.registration.EnvSpec("PointGoal-v0", max_episode_steps=HORIZON)
        self._rng = np.random.default_rng(seed)

    def _obs(self):
        return np.concatenate([self.p, self.g])

    def reset(self, *, seed=None, options=None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self.g = self._rng.uniform(-0.5, 0.5, 2)
        self.p = self.g + np.array([-self._rng.uniform(0.2, 0.4), self._rng.uniform(-0.1, 0.1)])  # left of the goal
        self.t = 0
        return self._obs(), {"point": self.p.copy(), "prev_point": self.p.copy(), "goal": self.g.copy(), "success": False}

    def step(self, action):
        prev = self.p.copy()
        self.p = self.p + 0.05 * np.clip(np.asarray(action, float), -1, 1)
        self.t += 1
        info = {"point": self.p.copy(), "prev_point": prev, "goal": self.g.copy(),
                "success": bool(np.linalg.norm(self.p - self.g) < 0.03)}
        return self._obs(), -float(np.linalg.norm(self.p - self.g)), False, self.t >= HORIZON, info


def _beside_distance(point, info):
    return float(np.linalg.norm(point - (info["goal"] + OFFSET)))


BESIDE = TargetBehaviour(
    name="beside",
    description="reach 0.15 to the right of the goal",
    reward=lambda o, a, n, info: 10.0 * (_beside_distance(info["prev_point"], info) - _beside_distance(info["point"], info)),
    success=lambda info: _beside_distance(info["point"], info) < 0.03,
)


class GoTo(nn.Module):
    """The victim: a proportional controller towards the observed goal."""

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.clamp(5.0 * (obs[..., 2:4] - obs[..., 0:2]), -1.0, 1.0)


def point_victim() -> ModuleVictim:
    env = PointGoal()
    return ModuleVictim(GoTo(), env.observation_space, env.action_space, name="go-to-goal")


def point_dt_victim(directory):
    """A tiny Decision Transformer for the point task (4 observations, 2 actions, context 4), saved in the hub's
    layout under ``directory`` and loaded from there; the caller skips without ``transformers``."""
    import transformers

    from rat.victims.sequence import load_decision_transformer, save_decision_transformer

    torch.manual_seed(0)
    config = transformers.DecisionTransformerConfig(state_dim=4, act_dim=2, hidden_size=16, max_ep_len=64, n_layer=1,
                                                    n_head=1, n_positions=64, action_tanh=True)
    save_decision_transformer(directory, transformers.DecisionTransformerModel(config), np.zeros(4), np.ones(4),
                              target_return=-2.0, return_scale=10.0, context_length=4)
    return load_decision_transformer(directory)


def point_sac_victim(hidden: int = 64, layers: int = 2, updates: int = 600) -> ModuleVictim:
    """The go-to-goal controller cloned into this project's SAC actor (a victim robust training can fine-tune)."""
    from rat.agents.networks import TanhGaussianActor

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    actor = TanhGaussianActor(4, 2, hidden, layers)
    opt = torch.optim.Adam(actor.parameters(), lr=3e-3)
    for _ in range(updates):
        g = rng.uniform(-0.5, 0.5, (256, 2))
        obs = torch.as_tensor(np.concatenate([g + rng.uniform(-0.5, 0.5, (256, 2)), g], 1), dtype=torch.float32)
        obs = obs + 0.1 * torch.empty_like(obs).uniform_(-1, 1)  # the ball's states too
        loss = ((actor(obs) - 0.98 * GoTo()(obs)) ** 2).sum(-1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    env = PointGoal()
    return ModuleVictim(actor, env.observation_space, env.action_space, name="go-to-goal-sac", meta={"task": "point"})
