"""Making victims: SAC from scratch (the paper's way), SAC warm-started with demonstrations,
and behaviour cloning of Meta-World's scripted experts.

Every method runs in a :class:`~rat.runs.Run` directory, checkpoints as it goes, resumes
from its last checkpoint when restarted with the same options, and ends by evaluating the
victim and saving it as ``victim.safetensors`` + ``victim.json``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from rat.agents.buffer import ReplayBuffer
from rat.agents.networks import TanhGaussianActor
from rat.agents.sac import SAC, SACConfig
from rat.checkpoint import load_checkpoint, save_checkpoint
from rat.envs.metaworld import make_task
from rat.eval import EvalResult, evaluate
from rat.errors import RatError
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
    bc_updates: int = 20_000  #: gradient steps of behaviour cloning
    bc_batch: int = 256  #: batch size of behaviour cloning
    bc_lr: float = 1e-3  #: Adam learning rate of behaviour cloning
    # SAC (sac, sac-demo)
    sac: SACConfig = field(default_factory=SACConfig)  #: SAC hyperparameters (paper's table 7)
    total_steps: int = 1_000_000  #: environment steps of SAC
    random_steps: int = 5_000  #: uniform random actions before learning (sac only)
    buffer_capacity: int = 1_000_000  #: replay buffer size
    eval_every: int = 10_000  #: environment steps between evaluations during SAC
    # evaluation and checkpoints
    eval_episodes: int = 50  #: final evaluation episodes
    checkpoint_every: int = 10_000  #: environment steps (SAC) or updates (BC) between checkpoints

    def __post_init__(self):
        if self.method not in METHODS:
            raise RatError(f"unknown victim method '{self.method}'; use one of: {', '.join(METHODS)}")
        for name in ("demo_episodes", "bc_updates", "total_steps", "eval_episodes", "checkpoint_every", "eval_every"):
            if getattr(self, name) <= 0:
                raise RatError(f"{name.replace('_', '-')} must be positive, got {getattr(self, name)}")
        if self.random_steps < 0 or self.demo_noise < 0:
            raise RatError("random-steps and demo-noise must not be negative")


# --- behaviour cloning -------------------------------------------------------------------------------


def bc_loss(actor: TanhGaussianActor, obs: torch.Tensor, expert_action: torch.Tensor) -> torch.Tensor:
    """Squared error between the actor's deterministic action and the expert's."""
    return ((actor(obs) - expert_action) ** 2).sum(-1).mean()


def behaviour_clone(actor: TanhGaussianActor, demos: Demonstrations, updates: int, batch: int,
                    optimizer: torch.optim.Optimizer, rng: np.random.Generator, start: int = 0,
                    on_chunk=None, chunk: int = 1000, progress: bool = False) -> int:
    """Fit ``actor`` to the demonstrations' labels; calls ``on_chunk(update, loss)`` every ``chunk`` updates."""
    obs = torch.as_tensor(demos.obs)
    act = torch.as_tensor(demos.action)
    bar = tqdm(total=updates, initial=start, desc="behaviour cloning", disable=not progress, leave=False)
    losses = []
    for update in range(start, updates):
        idx = torch.as_tensor(rng.integers(0, len(obs), size=batch))
        loss = bc_loss(actor, obs[idx], act[idx])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
        bar.update(1)
        if (update + 1) % chunk == 0 or update + 1 == updates:
            if on_chunk is not None:
                on_chunk(update + 1, float(np.mean(losses)))
            losses = []
    bar.close()
    return updates


def _demos_state(d: Demonstrations) -> dict:
    return {k: getattr(d, k) for k in ("obs", "action", "executed", "reward", "next_obs", "terminated")} | {
        "success_rate": d.success_rate}


def _get_demos(cfg: VictimConfig, env, rng, progress) -> Demonstrations:
    demos = collect_demonstrations(env, cfg.demo_episodes, cfg.demo_noise, rng, cfg.demo_episode_steps, progress)
    if demos.success_rate < 0.9:
        raise RatError(f"the scripted expert succeeded in only {demos.success_rate:.0%} of demonstrations on "
                       f"{cfg.task}; lower --demo-noise or use --method sac")
    return demos


def _train_bc(cfg: VictimConfig, run: Run, rng: np.random.Generator, env, progress: bool) -> TanhGaussianActor:
    actor = TanhGaussianActor(env.observation_space.shape[0], env.action_space.shape[0], cfg.hidden, cfg.layers)
    optimizer = torch.optim.Adam(actor.parameters(), lr=cfg.bc_lr)
    start = 0
    if run.has_checkpoint():
        state, meta = load_checkpoint(run.checkpoint_path, "victim-bc-run")
        actor.load_state_dict(state["actor"])
        optimizer.load_state_dict(state["optimizer"])
        restore_rng_state(rng, state["rng"])
        demos = Demonstrations(**state["demos"])
        start = int(meta["update"])
        run.logger.truncate_after(start)
    else:
        demos = _get_demos(cfg, env, rng, progress)
        run.logger.log(0, {"demo_success_rate": demos.success_rate, "demo_transitions": len(demos.obs)})

    def on_chunk(update: int, loss: float) -> None:
        run.logger.log(update, {"bc_loss": loss})
        if update % cfg.checkpoint_every == 0 or update == cfg.bc_updates:
            save_checkpoint(run.checkpoint_path, "victim-bc-run",
                            {"actor": actor.state_dict(), "optimizer": optimizer.state_dict(),
                             "rng": rng_state(rng), "demos": _demos_state(demos)}, {"update": update})

    chunk = math.gcd(1000, cfg.checkpoint_every)  # log every chunk; every checkpoint falls on a chunk's end
    behaviour_clone(actor, demos, cfg.bc_updates, cfg.bc_batch, optimizer, rng, start, on_chunk, chunk, progress)
    return actor


# --- SAC ---------------------------------------------------------------------------------------


def _train_sac(cfg: VictimConfig, run: Run, rng: np.random.Generator, env, progress: bool) -> TanhGaussianActor:
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    sac_cfg = replace(cfg.sac, hidden=cfg.hidden, layers=cfg.layers)
    agent = SAC(obs_dim, act_dim, sac_cfg)
    buffer = ReplayBuffer(obs_dim, act_dim, cfg.buffer_capacity)
    step, episode = 0, 0
    if run.has_checkpoint():
        state, meta = load_checkpoint(run.checkpoint_path, "victim-sac-run")
        agent.load_state_dict(state["agent"])
        agent.load_optimizer_state(state["optimizers"])
        buffer.load_state_dict(state["buffer"])
        restore_rng_state(rng, state["rng"])
        step, episode = int(meta["step"]), int(meta["episode"])
        run.logger.truncate_after(step)
    elif cfg.method == "sac-demo":
        demos = _get_demos(cfg, env, rng, progress)
        for i in range(len(demos.obs)):
            buffer.add(demos.obs[i], demos.executed[i], demos.reward[i], demos.next_obs[i], demos.terminated[i])
        opt = torch.optim.Adam(agent.actor.parameters(), lr=cfg.bc_lr)
        behaviour_clone(agent.actor, demos, cfg.bc_updates, cfg.bc_batch, opt, rng, progress=progress)
    random_steps = cfg.random_steps if cfg.method == "sac" else 0

    def checkpoint():
        save_checkpoint(run.checkpoint_path, "victim-sac-run",
                        {"agent": agent.state_dict(), "optimizers": agent.optimizer_state(),
                         "buffer": buffer.state_dict(), "rng": rng_state(rng)},
                        {"step": step, "episode": episode})

    bar = tqdm(total=cfg.total_steps, initial=step, desc=f"SAC {cfg.task}", disable=not progress)
    obs, _ = env.reset(seed=int(rng.integers(2**31)))
    ep_return, ep_success, t0, metrics = 0.0, False, time.perf_counter(), {}
    while step < cfg.total_steps:
        action = env.action_space.sample() if step < random_steps else agent.act(obs)
        next_obs, reward, terminated, truncated, info = env.step(action)
        buffer.add(obs, action, reward, next_obs, terminated)
        ep_return += reward
        ep_success |= info["success"]
        obs = next_obs
        step += 1
        bar.update(1)
        if step >= random_steps and len(buffer) >= sac_cfg.batch_size:
            metrics = agent.update(buffer.sample(sac_cfg.batch_size, rng))
        if terminated or truncated:
            episode += 1
            run.logger.log(step, {"episode_return": ep_return, "episode_success": float(ep_success),
                                  "steps_per_second": step / max(time.perf_counter() - t0, 1e-9), **metrics})
            obs, _ = env.reset(seed=int(rng.integers(2**31)))
            ep_return, ep_success = 0.0, False
        if step % cfg.eval_every == 0:
            res = evaluate(lambda o: agent.act(o, deterministic=True), make_task(cfg.task, seed=cfg.seed + 10**6),
                           10, seed=cfg.seed + 10**6 + step)
            run.logger.log(step, {"eval_success_rate": res.success_rate, "eval_return": res.mean_return})
            bar.set_postfix(success=f"{res.success_rate:.0%}")
        if step % cfg.checkpoint_every == 0:
            checkpoint()
    bar.close()
    return agent.actor


# --- the one entry point -------------------------------------------------------------------------


def train_victim(config: VictimConfig, out: str | Path, progress: bool = True, tensorboard: bool = False
                 ) -> tuple[Path, EvalResult]:
    """Make a victim with ``config`` in run directory ``out`` (resuming if it was interrupted).

    Returns the victim checkpoint's path and its clean evaluation over ``eval_episodes``.
    """
    run = Run(out, config, tensorboard)
    rng = seed_everything(config.seed)
    env = make_task(config.task, seed=config.seed)
    started = time.perf_counter()
    train = _train_bc if config.method == "bc" else _train_sac
    actor = train(config, run, rng, env, progress)
    train_seconds = time.perf_counter() - started

    victim = ModuleVictim(actor, env.observation_space, env.action_space, name=f"{config.task}:{config.method}")
    eval_env = make_task(config.task, seed=config.seed + 1)  # episodes never seen in training
    result = evaluate(numpy_policy(victim), eval_env, config.eval_episodes, seed=10**6 + config.seed, progress=progress)
    run.logger.log(config.total_steps if config.method != "bc" else config.bc_updates,
                   {"final_success_rate": result.success_rate, "final_return": result.mean_return})
    meta = {
        "task": config.task,
        "method": config.method,
        "config": run.config,
        "commit": git_commit(),
        "train_seconds": round(train_seconds, 1),
        "clean_eval": {k: v for k, v in result.to_dict().items() if k not in ("successes", "first_success_step")},
    }
    path = save_victim(run.dir / "victim", actor, env.observation_space, env.action_space, meta)
    return path, result
