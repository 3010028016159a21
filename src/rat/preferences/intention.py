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

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rat import seeds
from rat.device import resolve_device
from rat.envs import check_task, get_target, make_task
from rat.envs.physics import physics_of
from rat.envs.targets import TargetBehaviour
from rat.errors import RatError
from rat.eval import evaluate
from rat.loop import TrainingLoop, write_report
from rat.plots import plot_reward_quality, plot_training
from rat.preferences.labeller import Labeller
from rat.preferences.pebble import PebbleConfig, PebbleLearner
from rat.preferences.reward_model import reward_agreement
from rat.preferences.segments import EpisodeHistory
from rat.preferences.store import LabelStore
from rat.reports import IntentionReport
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
    device: str = "auto"  #: auto (a GPU when torch sees one), cpu or cuda

    def __post_init__(self):
        for name in ("total_steps", "eval_every", "eval_episodes", "final_eval_episodes", "quality_episodes",
                     "checkpoint_every"):
            if getattr(self, name) <= 0:
                raise RatError(f"{name.replace('_', '-')} must be positive, got {getattr(self, name)}")
        self.pebble.check_steps(self.total_steps, "the intention policy")
        self.pebble.check_budget("the intention policy")


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
    pearson = reward_agreement(r_hat, r_true, segment_length).get("step_corr", float("nan"))
    return RewardQuality(accuracy, int(decided.sum()), pearson, len(r_true))


class IntentionTrainer:
    """PEBBLE alone in the target's environment, one environment step at a time (a :class:`~rat.loop.Trainer`)."""

    kind = "intention-run"

    def __init__(self, config: IntentionConfig, target: TargetBehaviour, env_task: str, store: LabelStore,
                 source: str, labeller: Labeller | None = None):
        self.config, self.target, self.env_task = config, target, env_task
        self.rng = seed_everything(config.seed)
        self.env = env = make_task(env_task, seed=config.seed)
        obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
        self.learner = PebbleLearner(obs_dim, act_dim, config.pebble, store, source=source, rng=self.rng,
                                     labeller=labeller, task=env_task, target=config.target,
                                     device=resolve_device(config.device))
        self.obs: np.ndarray | None = None
        self.finished = False

    @property
    def step(self) -> int:
        return self.learner.step

    def advance(self) -> dict[str, float] | None:
        learner = self.learner
        if self.obs is None:
            self.obs, _ = self.env.reset(seed=int(self.rng.integers(2**31)))
            self.ep_return, self.succeeded, self.metrics = 0.0, False, {}
            self.success_test = self.target.episode_success()
        obs = self.obs
        action = learner.act(obs)
        physics = physics_of(self.env) if learner.wants_physics else None  # to film the step for a person
        next_obs, _, terminated, truncated, info = self.env.step(action)
        r_target = self.target.reward(obs, action, next_obs, info)
        self.metrics.update(learner.observe(obs, action, next_obs, r_target, terminated, truncated, physics))
        self.ep_return += r_target
        self.succeeded |= self.success_test(info)
        self.obs = next_obs
        if terminated or truncated:
            self.obs = None
            return {"target_return": self.ep_return, "target_success": float(self.succeeded), **self.metrics}
        return None

    def evaluate(self) -> dict[str, float]:
        cfg, learner = self.config, self.learner
        res = evaluate(lambda o: learner.act(o, deterministic=True), make_task(self.env_task, seed=cfg.seed + seeds.EVAL_ENV),
                       cfg.eval_episodes, seed=seeds.periodic(self.step), target=self.target)
        return {"eval_success_rate": res.success_rate, "labels": learner.store.count(learner.source)}

    def state_dict(self) -> dict:
        return {"learner": self.learner.state_dict(), "rng": rng_state(self.rng)}

    def load_state_dict(self, state: dict, meta: dict) -> None:
        self.learner.load_state_dict(state["learner"])
        self.learner.restore_meta(meta)
        restore_rng_state(self.rng, state["rng"])

    def checkpoint_meta(self) -> dict:
        return self.learner.checkpoint_meta()


def train_intention(config: IntentionConfig, out: str | Path, progress: bool = True, tensorboard: bool = False,
                    labeller: Labeller | None = None) -> IntentionReport:
    """Train an intention policy from preference labels in run directory ``out`` (resumable).

    Returns the report (also written to ``out/report.json``).
    """
    target = get_target(config.target)
    env_task = check_task(target.env_task(check_task(config.task)))
    run = Run(out, config, tensorboard)
    store = LabelStore(run.dir / "labels.sqlite")
    trainer = IntentionTrainer(config, target, env_task, store, run.dir.name, labeller)
    learner = trainer.learner
    loop = TrainingLoop(run, trainer, config.total_steps, eval_every=config.eval_every,
                        checkpoint_every=config.checkpoint_every, desc=f"intention {config.target} on {env_task}",
                        progress=progress)
    loop.resume()
    train_seconds = loop.run()

    fresh = make_task(env_task, seed=config.seed + seeds.FRESH_ENV)
    final = evaluate(lambda o: learner.act(o, deterministic=True), fresh, config.final_eval_episodes,
                     seed=seeds.FINAL, target=target, progress=progress)
    episodes = rollouts(lambda o: learner.agent.act(o), fresh, target, config.quality_episodes, seed=seeds.SELECTION)
    quality = reward_quality(learner.ensemble, episodes, config.pebble.segment_length, 500,
                             np.random.default_rng(seeds.SELECTION + config.seed))  # held-out pairs of their own
    title = f"{config.target} on {env_task}: {learner.store.count(learner.source)} labels"
    plot_reward_quality(episodes[0], learner.ensemble.r_hat(episodes[0]["obs"], episodes[0]["action"]),
                        run.dir / "reward_quality.png", title)
    plot_training(run.logger.path, run.dir / "training.png", f"intention policy: {title}")
    report = IntentionReport(
        task=env_task, victim_task=config.task, target=config.target, steps=learner.step,
        queries_asked=learner.asked, labels=store.count(learner.source),
        target_success_rate=final.success_rate, target_success_ci=list(final.success_ci),
        final_eval_episodes=final.episodes, preference_accuracy=quality.preference_accuracy,
        held_out_pairs=quality.held_out_pairs, reward_pearson=quality.pearson, quality_steps=quality.steps,
        train_minutes_this_session=round(train_seconds / 60, 2), train_minutes=round(loop.total_seconds / 60, 2))
    write_report(run.dir, report)
    store.close()
    return report
