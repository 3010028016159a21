"""Training an intention policy alone (no victim), and judging what it learned.

``train_intention`` runs PEBBLE in the target behaviour's environment and reports:

- the intention policy's target success rate (deterministic actions, fresh episodes);
- the learned reward's quality: preference accuracy of r̂ on held-out segment pairs (labelled
  by a noise-free teacher, ties left out) and the Pearson correlation of r̂ with the true target
  reward along fresh rollouts;
- a plot of the learned and the true reward along one rollout (both standardised), the
  paper's "quality of learned reward" figure.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import stats
from tqdm.auto import tqdm

from rat.checkpoint import load_checkpoint, save_checkpoint
from rat.envs import check_task, get_target, make_task
from rat.envs.targets import TargetBehaviour
from rat.errors import RatError
from rat.eval import evaluate
from rat.preferences.pebble import PebbleConfig, PebbleLearner
from rat.preferences.segments import EpisodeHistory
from rat.plots import plot_reward_quality, plot_training
from rat.preferences.store import LabelStore
from rat.runs import Run, restore_rng_state, rng_state, seed_everything


@dataclass(frozen=True)
class IntentionConfig:
    """An intention-policy run."""

    task: str = "drawer-open-v3"  #: the victim's task; the environment is the target's choice for it
    target: str = "reach"  #: target behaviour to learn from labels
    seed: int = 0  #: seeds everything
    total_steps: int = 100_000  #: environment steps
    pebble: PebbleConfig = field(default_factory=PebbleConfig)  #: PEBBLE settings
    eval_every: int = 10_000  #: steps between evaluations during training
    eval_episodes: int = 10  #: episodes per evaluation during training
    final_eval_episodes: int = 30  #: episodes of the final evaluation
    quality_episodes: int = 5  #: fresh rollouts for the reward-quality report
    checkpoint_every: int = 5_000  #: steps between checkpoints

    def __post_init__(self):
        for name in ("total_steps", "eval_every", "eval_episodes", "final_eval_episodes", "quality_episodes",
                     "checkpoint_every"):
            if getattr(self, name) <= 0:
                raise RatError(f"{name.replace('_', '-')} must be positive, got {getattr(self, name)}")


@dataclass
class RewardQuality:
    preference_accuracy: float  # on held-out pairs, ties excluded
    held_out_pairs: int
    pearson: float  # r̂ vs true target reward per step of fresh rollouts
    steps: int


def rollouts(policy, env, target: TargetBehaviour, episodes: int, seed: int) -> list[dict[str, np.ndarray]]:
    """Episodes of ``policy`` with observations, actions and true target rewards."""
    out = []
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed + ep)
        rows = {"obs": [], "action": [], "reward": []}
        done = False
        while not done:
            action = policy(obs)
            next_obs, _, terminated, truncated, info = env.step(action)
            rows["obs"].append(obs)
            rows["action"].append(action)
            rows["reward"].append(target.reward(obs, action, next_obs, info))
            obs, done = next_obs, terminated or truncated
        out.append({k: np.asarray(v, np.float32) for k, v in rows.items()})
    return out


def reward_quality(ensemble, episodes: list[dict[str, np.ndarray]], segment_length: int, pairs: int,
                   rng: np.random.Generator) -> RewardQuality:
    """Judge r̂ against the true target reward on episodes it was not trained on."""
    history = EpisodeHistory(len(episodes))
    for e in episodes:
        for t in range(len(e["obs"])):
            history.add(e["obs"][t], e["action"][t], e["reward"][t], t == len(e["obs"]) - 1)
    p = history.sample_pairs(pairs, segment_length, rng)
    true_diff = p.reward1.sum(1) - p.reward0.sum(1)
    learned_diff = ensemble.r_hat(p.obs1, p.act1).sum(1) - ensemble.r_hat(p.obs0, p.act0).sum(1)
    decided = np.abs(true_diff) > 1e-6
    accuracy = float(np.mean(np.sign(true_diff[decided]) == np.sign(learned_diff[decided]))) if decided.any() else float("nan")
    r_true = np.concatenate([e["reward"] for e in episodes])
    r_hat = np.concatenate([ensemble.r_hat(e["obs"], e["action"]) for e in episodes])
    pearson = float(stats.pearsonr(r_hat, r_true)[0]) if np.std(r_true) > 0 and np.std(r_hat) > 0 else float("nan")
    return RewardQuality(accuracy, int(decided.sum()), pearson, len(r_true))


def train_intention(config: IntentionConfig, out: str | Path, progress: bool = True, tensorboard: bool = False) -> dict:
    """Train an intention policy from preference labels in run directory ``out`` (resumable).

    Returns the report (also written to ``out/report.json``).
    """
    target = get_target(config.target)
    env_task = check_task(target.env_task(check_task(config.task)))
    run = Run(out, config, tensorboard)
    rng = seed_everything(config.seed)
    env = make_task(env_task, seed=config.seed)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    store = LabelStore(run.dir / "labels.sqlite")
    learner = PebbleLearner(obs_dim, act_dim, config.pebble, store, source=run.dir.name, rng=rng,
                            task=env_task, target=config.target)
    if run.has_checkpoint():
        state, _ = load_checkpoint(run.checkpoint_path, "intention-run")
        learner.load_state_dict(state["learner"])
        restore_rng_state(rng, state["rng"])
        run.logger.truncate_after(learner.step)

    def checkpoint():
        save_checkpoint(run.checkpoint_path, "intention-run", {"learner": learner.state_dict(), "rng": rng_state(rng)},
                        {"step": learner.step})

    started = time.perf_counter()
    bar = tqdm(total=config.total_steps, initial=learner.step, desc=f"intention {config.target} on {env_task}",
               disable=not progress)
    obs, _ = env.reset(seed=int(rng.integers(2**31)))
    ep_return, ep_success, metrics = 0.0, False, {}
    while learner.step < config.total_steps:
        action = learner.act(obs)
        next_obs, _, terminated, truncated, info = env.step(action)
        r_target = target.reward(obs, action, next_obs, info)
        metrics.update(learner.observe(obs, action, next_obs, r_target, terminated, truncated))
        ep_return += r_target
        ep_success |= target.success(info)
        obs = next_obs
        bar.update(1)
        if terminated or truncated:
            run.logger.log(learner.step, {"target_return": ep_return, "target_success": float(ep_success), **metrics})
            obs, _ = env.reset(seed=int(rng.integers(2**31)))
            ep_return, ep_success, metrics = 0.0, False, {}
        if learner.step % config.eval_every == 0:
            res = evaluate(lambda o: learner.act(o, deterministic=True), make_task(env_task, seed=config.seed + 7),
                           config.eval_episodes, seed=10**7 + learner.step, target=target)
            run.logger.log(learner.step, {"eval_success_rate": res.success_rate, "labels": learner.store.count(learner.source)})
            bar.set_postfix(success=f"{res.success_rate:.0%}", labels=learner.asked)
        if learner.step % config.checkpoint_every == 0:
            checkpoint()
    bar.close()
    train_seconds = time.perf_counter() - started

    fresh = make_task(env_task, seed=config.seed + 1)
    final = evaluate(lambda o: learner.act(o, deterministic=True), fresh, config.final_eval_episodes,
                     seed=2 * 10**7, target=target, progress=progress)
    episodes = rollouts(lambda o: learner.agent.act(o), fresh, target, config.quality_episodes, seed=3 * 10**7)
    quality = reward_quality(learner.ensemble, episodes, config.pebble.segment_length, 500, rng)
    title = f"{config.target} on {env_task}: {learner.store.count(learner.source)} labels"
    plot_reward_quality(episodes[0], learner.ensemble.r_hat(episodes[0]["obs"], episodes[0]["action"]),
                        run.dir / "reward_quality.png", title)
    plot_training(run.logger.path, run.dir / "training.png", f"intention policy: {title}")
    report = {
        "task": env_task, "victim_task": config.task, "target": config.target, "steps": learner.step,
        "queries_asked": learner.asked, "labels": store.count(learner.source),
        "target_success_rate": final.success_rate, "target_success_ci": list(final.success_ci),
        "final_eval_episodes": final.episodes,
        "preference_accuracy": quality.preference_accuracy, "held_out_pairs": quality.held_out_pairs,
        "reward_pearson": quality.pearson, "quality_steps": quality.steps,
        "train_minutes_this_session": round(train_seconds / 60, 2),
    }
    (run.dir / "report.json").write_text(json.dumps(report, indent=1))
    store.close()
    return report
