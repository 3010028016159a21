"""Making victims: SAC from scratch (the paper's way), SAC warm-started with demonstrations,
and behaviour cloning of Meta-World's scripted experts.

Every method runs in a :class:`~rat.runs.Run` directory, checkpoints as it goes, resumes
from its last checkpoint when restarted with the same options, and ends by evaluating the
victim and saving it as ``victim.safetensors`` + ``victim.json``.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from rat import seeds
from rat.agents.buffer import ReplayBuffer
from rat.agents.networks import TanhGaussianActor
from rat.agents.sac import SAC, SACConfig
from rat.device import resolve_device
from rat.envs import LOCOMOTION_TASKS, make_task
from rat.errors import RatError
from rat.eval import EvalResult, evaluate
from rat.loop import TrainingLoop
from rat.runs import Run, git_commit, restore_rng_state, rng_state, seed_everything
from rat.victims.adapters import save_victim
from rat.victims.base import ModuleVictim, numpy_policy
from rat.victims.experts import Demonstrations, collect_demonstrations

METHODS = {
    "sac": "SAC from scratch on the task reward (the paper's victims; 1e6 steps by default)",
    "sac-demo": "SAC on the task reward, warm-started by behaviour cloning and a buffer of expert demonstrations",
    "bc": "behaviour cloning of Meta-World's scripted expert with DART noise (minutes on a CPU)",
}


@dataclass(frozen=True)
class VictimConfig:
    """How to make one victim. Fields not used by the chosen method are ignored."""

    task: str = "drawer-open-v3"  #: Meta-World v3 task
    method: str = "bc"  #: one of ``METHODS``
    seed: int = 0  #: seeds everything: environment draws, networks, sampling
    hidden: int = 256  #: actor width
    layers: int = 3  #: actor hidden layers
    # demonstrations (bc, sac-demo)
    demo_episodes: int = 100  #: expert episodes to collect
    demo_noise: float = 0.3  #: std of Gaussian noise on executed expert actions (DART)
    demo_episode_steps: int = 200  #: steps kept per demonstration episode (experts finish in 45-120)
    # behaviour cloning (bc, and the warm start of sac-demo)
    bc_updates: int = 20_000  #: gradient steps of behaviour cloning (sac-demo: 0 seeds only the replay buffer)
    bc_batch: int = 256  #: batch size of behaviour cloning
    bc_lr: float = 1e-3  #: Adam learning rate of behaviour cloning
    # SAC (sac, sac-demo)
    sac: SACConfig = field(default_factory=SACConfig)  #: SAC hyperparameters (paper's table 7)
    total_steps: int = 1_000_000  #: environment steps of SAC
    random_steps: int = 5_000  #: uniform random actions before learning (sac only)
    buffer_capacity: int = 1_000_000  #: replay buffer size
    eval_every: int = 10_000  #: environment steps between evaluations during SAC
    eval_every_episodes: int = 10  #: episodes of each evaluation during SAC
    stop_success: float | None = None  #: end SAC early once this many evaluations in a row reach this success rate
    stop_patience: int = 3  #: consecutive evaluations at ``stop_success`` that end SAC early
    keep: str = "best"  #: the SAC actor saved: the "best" evaluated (by success, then return) or the "last"
    # evaluation and checkpoints
    eval_episodes: int = 50  #: final evaluation episodes
    checkpoint_every: int = 10_000  #: environment steps (SAC) or updates (BC) between checkpoints
    device: str = "auto"  #: auto (a GPU when torch sees one), cpu or cuda

    def __post_init__(self):
        if self.method not in METHODS:
            raise RatError(f"unknown victim method '{self.method}'; use one of: {', '.join(METHODS)}")
        for name in ("demo_episodes", "total_steps", "eval_episodes", "checkpoint_every", "eval_every",
                     "eval_every_episodes", "stop_patience"):
            if getattr(self, name) <= 0:
                raise RatError(f"{name.replace('_', '-')} must be positive, got {getattr(self, name)}")
        if self.bc_updates < 0 or (self.bc_updates == 0 and self.method == "bc"):
            raise RatError(f"bc-updates must be positive for bc (0 is allowed for sac-demo), got {self.bc_updates}")
        if self.stop_success is not None and not 0 < self.stop_success <= 1:
            raise RatError(f"stop-success must lie in (0, 1], got {self.stop_success}")
        if self.keep not in ("best", "last"):
            raise RatError(f"keep must be best or last, got '{self.keep}'")
        if self.random_steps < 0 or self.demo_noise < 0:
            raise RatError("random-steps and demo-noise must not be negative")
        if self.method != "sac" and self.task in LOCOMOTION_TASKS:
            raise RatError(f"{self.task} has no scripted expert to learn from; use --method sac")
        if self.method == "sac" and self.total_steps <= self.random_steps:
            raise RatError(f"{self.total_steps} steps end before SAC's first update (after {self.random_steps} random "
                           f"steps); give --total-steps > {self.random_steps} or --set random_steps=...")


# --- behaviour cloning -------------------------------------------------------------------------------


def bc_loss(actor: TanhGaussianActor, obs: torch.Tensor, expert_action: torch.Tensor) -> torch.Tensor:
    """Squared error between the actor's deterministic action and the expert's."""
    return ((actor(obs) - expert_action) ** 2).sum(-1).mean()


def bc_update(actor: TanhGaussianActor, optimizer: torch.optim.Optimizer, obs: torch.Tensor, action: torch.Tensor,
              batch: int, rng: np.random.Generator) -> float:
    """One behaviour-cloning step on a random batch of the labelled states; returns its loss."""
    idx = torch.as_tensor(rng.integers(0, len(obs), size=batch))
    loss = bc_loss(actor, obs[idx], action[idx])
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    return loss.item()


def behaviour_clone(actor: TanhGaussianActor, demos: Demonstrations, updates: int, batch: int,
                    optimizer: torch.optim.Optimizer, rng: np.random.Generator, progress: bool = False) -> None:
    """Fit ``actor`` to the demonstrations' labels with ``updates`` steps (SAC's optional warm start)."""
    device = next(actor.parameters()).device
    obs, act = torch.as_tensor(demos.obs, device=device), torch.as_tensor(demos.action, device=device)
    for _ in tqdm(range(updates), desc="behaviour cloning", disable=not progress, leave=False):
        bc_update(actor, optimizer, obs, act, batch, rng)


def _demos_state(d: Demonstrations) -> dict:
    return {k: getattr(d, k) for k in ("obs", "action", "executed", "reward", "next_obs", "terminated")} | {
        "success_rate": d.success_rate}


def _get_demos(cfg: VictimConfig, env, rng, progress) -> Demonstrations:
    demos = collect_demonstrations(env, cfg.demo_episodes, cfg.demo_noise, rng, cfg.demo_episode_steps, progress)
    if demos.success_rate < 0.9:
        raise RatError(f"the scripted expert succeeded in only {demos.success_rate:.0%} of demonstrations on "
                       f"{cfg.task}; lower --demo-noise or use --method sac")
    return demos


class BCTrainer:
    """Behaviour cloning of the scripted expert, one gradient step at a time (a :class:`~rat.loop.Trainer`)."""

    kind = "victim-bc-run"

    def __init__(self, cfg: VictimConfig, run: Run, rng: np.random.Generator, env, progress: bool):
        self.cfg, self.run, self.rng, self.env, self.progress = cfg, run, rng, env, progress
        self.device = resolve_device(cfg.device)
        self.actor = TanhGaussianActor(env.observation_space.shape[0], env.action_space.shape[0], cfg.hidden,
                                       cfg.layers).to(self.device)
        self.optimizer = torch.optim.Adam(self.actor.parameters(), lr=cfg.bc_lr)
        self.demos: Demonstrations | None = None
        self.step, self.finished, self.losses = 0, False, []
        self.chunk = math.gcd(1000, cfg.checkpoint_every)  # log every chunk; every checkpoint falls on a chunk's end

    def _set_demos(self, demos: Demonstrations) -> None:
        self.demos = demos
        self.obs = torch.as_tensor(demos.obs, device=self.device)
        self.action = torch.as_tensor(demos.action, device=self.device)

    def advance(self) -> dict[str, float] | None:
        if self.demos is None:
            self._set_demos(_get_demos(self.cfg, self.env, self.rng, self.progress))
            self.run.logger.log(0, {"demo_success_rate": self.demos.success_rate,
                                    "demo_transitions": len(self.demos.obs)})
        self.losses.append(bc_update(self.actor, self.optimizer, self.obs, self.action, self.cfg.bc_batch, self.rng))
        self.step += 1
        if self.step % self.chunk == 0 or self.step == self.cfg.bc_updates:
            loss, self.losses = float(np.mean(self.losses)), []
            return {"bc_loss": loss}
        return None

    def evaluate(self) -> dict[str, float]:
        return {}

    def state_dict(self) -> dict:
        return {"actor": self.actor.state_dict(), "optimizer": self.optimizer.state_dict(), "rng": rng_state(self.rng),
                "demos": _demos_state(self.demos)}

    def load_state_dict(self, state: dict, meta: dict) -> None:
        self.actor.load_state_dict(state["actor"])
        self.optimizer.load_state_dict(state["optimizer"])
        restore_rng_state(self.rng, state["rng"])
        self._set_demos(Demonstrations(**state["demos"]))
        self.step = int(meta["update"])

    def checkpoint_meta(self) -> dict:
        return {"update": self.step}


# --- SAC ---------------------------------------------------------------------------------------


class SACVictimTrainer:
    """SAC on the task reward, one environment step at a time (a :class:`~rat.loop.Trainer`).

    ``sac-demo`` seeds the replay buffer with scripted demonstrations (and, with ``bc_updates``,
    warm-starts the actor by behaviour cloning) before the first step; ``stop_success`` ends
    training once ``stop_patience`` evaluations in a row reach it. SAC on Meta-World is not
    monotone (evaluations swing between 30% and 100% late in training), so with ``keep="best"``
    the actor of the best evaluation so far is kept beside the learner, and is the one saved.
    """

    kind = "victim-sac-run"

    def __init__(self, cfg: VictimConfig, run: Run, rng: np.random.Generator, env, progress: bool):
        self.cfg, self.run, self.rng, self.env, self.progress = cfg, run, rng, env, progress
        self.device = resolve_device(cfg.device)
        obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
        self.sac_cfg = replace(cfg.sac, hidden=cfg.hidden, layers=cfg.layers)
        self.agent = SAC(obs_dim, act_dim, self.sac_cfg, device=self.device)
        self.buffer = ReplayBuffer(obs_dim, act_dim, cfg.buffer_capacity)
        self.step, self.episode, self.streak, self.started = 0, 0, 0, False
        self.random_steps = cfg.random_steps if cfg.method == "sac" else 0
        self.obs: np.ndarray | None = None
        self.t0, self.t0_step, self.metrics = time.perf_counter(), 0, {}
        self.best: dict | None = None  # {"score": (success, return), "step", "actor": state dict} (keep="best")

    @property
    def finished(self) -> bool:
        return self.streak >= self.cfg.stop_patience

    def _warm_start(self) -> None:
        cfg = self.cfg
        if cfg.method == "sac-demo":
            demos = _get_demos(cfg, self.env, self.rng, self.progress)
            for i in range(len(demos.obs)):
                self.buffer.add(demos.obs[i], demos.executed[i], demos.reward[i], demos.next_obs[i],
                                demos.terminated[i])
            if cfg.bc_updates > 0:
                opt = torch.optim.Adam(self.agent.actor.parameters(), lr=cfg.bc_lr)
                behaviour_clone(self.agent.actor, demos, cfg.bc_updates, cfg.bc_batch, opt, self.rng, self.progress)
        self.started = True

    def advance(self) -> dict[str, float] | None:
        if not self.started:
            self._warm_start()
        if self.obs is None:
            self.obs, _ = self.env.reset(seed=int(self.rng.integers(2**31)))
            self.ep_return, self.succeeded = 0.0, False
        obs = self.obs
        action = self.env.action_space.sample() if self.step < self.random_steps else self.agent.act(obs)
        next_obs, reward, terminated, truncated, info = self.env.step(action)
        self.buffer.add(obs, action, reward, next_obs, terminated)
        self.ep_return += reward
        self.succeeded |= info["success"]
        self.obs = next_obs
        self.step += 1
        if self.step >= self.random_steps and len(self.buffer) >= self.sac_cfg.batch_size:
            self.metrics = self.agent.update(self.buffer.sample(self.sac_cfg.batch_size, self.rng, self.device))
        if terminated or truncated:
            self.episode += 1
            self.obs = None
            return {"episode_return": self.ep_return, "episode_success": float(self.succeeded),
                    "steps_per_second": (self.step - self.t0_step) / max(time.perf_counter() - self.t0, 1e-9), **self.metrics}
        return None

    def evaluate(self) -> dict[str, float]:
        cfg = self.cfg
        env = make_task(cfg.task, seed=cfg.seed + seeds.VICTIM_EVAL_ENV)
        res = evaluate(lambda o: self.agent.act(o, deterministic=True), env, cfg.eval_every_episodes,
                       seed=cfg.seed + seeds.VICTIM_EVAL_ENV + self.step)
        reached = cfg.stop_success is not None and res.success_rate >= cfg.stop_success
        self.streak = self.streak + 1 if reached else 0
        score = (res.success_rate, res.mean_return)
        if cfg.keep == "best" and (self.best is None or score >= tuple(self.best["score"])):
            actor = {k: v.detach().cpu().clone() for k, v in self.agent.actor.state_dict().items()}
            self.best = {"score": list(score), "step": self.step, "actor": actor}
        return {"eval_success_rate": res.success_rate, "eval_return": res.mean_return}

    def state_dict(self) -> dict:
        return {"agent": self.agent.state_dict(), "optimizers": self.agent.optimizer_state(),
                "buffer": self.buffer.state_dict(), "rng": rng_state(self.rng), "best": self.best}

    def load_state_dict(self, state: dict, meta: dict) -> None:
        self.agent.load_state_dict(state["agent"])
        self.agent.load_optimizer_state(state["optimizers"])
        self.buffer.load_state_dict(state["buffer"])
        restore_rng_state(self.rng, state["rng"])
        self.best = state.get("best")  # None (not stored) until the first evaluation
        self.step, self.episode = int(meta["step"]), int(meta["episode"])
        self.streak, self.started = int(meta.get("streak", 0)), True
        self.t0, self.t0_step = time.perf_counter(), self.step  # speed of this session

    def checkpoint_meta(self) -> dict:
        return {"episode": self.episode, "streak": self.streak}

    @property
    def actor(self) -> TanhGaussianActor:
        """The actor to save: the best evaluated one (``keep="best"``, once evaluated) or the learner's."""
        if self.best is None:
            return self.agent.actor
        actor = copy.deepcopy(self.agent.actor)
        actor.load_state_dict(self.best["actor"])
        return actor

    @property
    def kept(self) -> dict:
        """What was kept, for the victim's metadata."""
        if self.best is None:
            return {"kept": "last", "kept_step": self.step}
        return {"kept": "best", "kept_step": self.best["step"], "kept_eval_success_rate": self.best["score"][0]}


# --- the one entry point -------------------------------------------------------------------------


def clean_evaluation(victim, task: str, seed: int, episodes: int, progress: bool = False) -> EvalResult:
    """A victim's clean evaluation as the zoo reports it: ``episodes`` episodes on environment instances that
    training with ``seed`` never saw, counted as success at any step."""
    env = make_task(task, seed=seed + seeds.FRESH_ENV)
    return evaluate(numpy_policy(victim), env, episodes, seed=seeds.VICTIM_FINAL + seed, progress=progress)


def train_victim(config: VictimConfig, out: str | Path, progress: bool = True, tensorboard: bool = False
                 ) -> tuple[Path, EvalResult]:
    """Make a victim with ``config`` in run directory ``out`` (resuming if it was interrupted).

    Returns the victim checkpoint's path and its clean evaluation over ``eval_episodes``.
    """
    run = Run(out, config, tensorboard)
    rng = seed_everything(config.seed)
    env = make_task(config.task, seed=config.seed)
    if config.method == "bc":
        trainer, total, eval_every = BCTrainer(config, run, rng, env, progress), config.bc_updates, None
    else:
        trainer, total, eval_every = SACVictimTrainer(config, run, rng, env, progress), config.total_steps, config.eval_every
    loop = TrainingLoop(run, trainer, total, eval_every=eval_every, checkpoint_every=config.checkpoint_every,
                        checkpoint_at_boundary=config.method == "bc", desc=f"{config.method} {config.task}",
                        progress=progress)
    loop.resume()
    loop.run()
    actor = trainer.actor.cpu()

    victim = ModuleVictim(actor, env.observation_space, env.action_space, name=f"{config.task}:{config.method}")
    result = clean_evaluation(victim, config.task, config.seed, config.eval_episodes, progress)
    run.logger.log(trainer.step, {"final_success_rate": result.success_rate, "final_return": result.mean_return})
    meta = {
        "task": config.task,
        "method": config.method,
        "config": run.config,
        "commit": git_commit(),
        "train_seconds": round(loop.total_seconds, 1),  # every session's, when it resumed
        **getattr(trainer, "kept", {}),
        "clean_eval": {k: v for k, v in result.to_dict().items() if k not in ("successes", "first_success_step")},
    }
    path = save_victim(run.dir / "victim", actor, env.observation_space, env.action_space, meta)
    return path, result
