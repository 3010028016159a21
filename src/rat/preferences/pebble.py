"""PEBBLE: SAC on a reward learned from preferences, with unsupervised pre-training.

:class:`PebbleLearner` owns the intention policy (SAC), its replay buffer, the reward
ensemble and the query schedule. It does not own an environment: whoever collects data calls
:meth:`PebbleLearner.observe` with each transition (the intention-policy trainer acts with
:meth:`PebbleLearner.act`; RAT acts with its combined behaviour policy), and the learner does
the rest, by environment step:

1. steps ``[0, seed_steps)``: uniform random actions, no updates;
2. steps ``[seed_steps, first round)``: SAC on the state-entropy intrinsic reward;
3. the first round: uniform queries, reward training, relabel the whole buffer, reset the
   critic, ``reset_updates`` SAC updates;
4. then every ``feedback_every`` steps while the budget lasts: a round of ``per_round``
   queries chosen by ``strategy`` from ``candidates_factor × per_round`` candidates, reward
   training, relabelling of the whole buffer; SAC on r̂ throughout.

Every label goes to a :class:`~rat.preferences.store.LabelStore` as it arrives.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from rat.agents.buffer import ReplayBuffer
from rat.agents.exploration import RunningMeanStd, state_entropy_reward
from rat.agents.sac import SAC, SACConfig
from rat.errors import RatError
from rat.preferences.labeller import Labeller, QueryRound
from rat.preferences.queries import STRATEGIES, pair_features, select_queries
from rat.preferences.reward_model import RewardEnsemble, RewardModelConfig, reward_agreement
from rat.preferences.schedule import FeedbackSchedule
from rat.preferences.segments import EpisodeHistory
from rat.preferences.store import LabelStore
from rat.preferences.teacher import ScriptedTeacher, TeacherConfig


def _intention_sac() -> SACConfig:
    return SACConfig(lr=3e-4, alpha_lr=1e-4, init_temperature=0.1, batch_size=1024)


@dataclass(frozen=True)
class PebbleConfig:
    """PEBBLE settings (defaults: the paper's appendix A.3 and ``docs/design.md`` §4)."""

    sac: SACConfig = field(default_factory=_intention_sac)  #: intention policy's SAC
    seed_steps: int = 1_000  #: uniform random actions first
    unsupervised_steps: int = 9_000  #: state-entropy pre-training after the seed steps
    budget: int = 3_000  #: preference queries in all
    feedback_every: int = 5_000  #: steps between query rounds after the first
    per_round: int = 128  #: queries per round
    candidates_factor: int = 10  #: candidates drawn per query asked
    first_strategy: str = "uniform"  #: query strategy of the first round
    strategy: str = "disagreement"  #: query strategy of later rounds
    segment_length: int = 50  #: steps per segment
    max_episodes: int = 100  #: recent episodes segments are drawn from
    reward: RewardModelConfig = field(default_factory=RewardModelConfig)  #: reward ensemble
    teacher: TeacherConfig = field(default_factory=TeacherConfig)  #: scripted teacher's noise
    entropy_k: int = 5  #: k of the k-NN state entropy
    reset_updates: int = 100  #: SAC updates right after the critic reset
    updates_per_step: float = 1.0  #: SAC updates per environment step (0.5: one every other step; 2: two a step)
    buffer_capacity: int = 1_000_000  #: replay buffer size
    oracle: bool = False  #: learn from the true target reward instead of labels (an upper bound; no queries)

    def __post_init__(self):
        for name in ("seed_steps", "unsupervised_steps", "reset_updates", "updates_per_step"):
            if not getattr(self, name) >= 0 or math.isinf(getattr(self, name)):  # NaN fails the first test
                raise RatError(f"{name.replace('_', '-')} must be a finite number >= 0, got {getattr(self, name)}")
        for name in ("segment_length", "candidates_factor", "max_episodes", "buffer_capacity"):
            if getattr(self, name) <= 0:
                raise RatError(f"{name.replace('_', '-')} must be positive, got {getattr(self, name)}")
        for name in ("first_strategy", "strategy"):
            if getattr(self, name) not in STRATEGIES:
                raise RatError(f"unknown query strategy '{getattr(self, name)}'; use one of: {', '.join(STRATEGIES)}")
        _ = self.schedule  # validates budget and round settings

    @property
    def warm_up(self) -> int:
        """Steps before the target behaviour is first learnt: seed steps plus pre-training (the first round's step)."""
        return self.seed_steps + self.unsupervised_steps

    def check_steps(self, total_steps: int, what: str) -> None:
        """A one-line error if ``total_steps`` end before the first query round, when nothing would be learnt."""
        if total_steps <= self.warm_up:
            raise RatError(f"{total_steps} steps end before {what} learns anything: the first labels come at step "
                           f"{self.warm_up} (seed steps {self.seed_steps} + pre-training {self.unsupervised_steps}); "
                           f"give --steps > {self.warm_up}, a shorter warm-up (--seed-steps, --pretrain-steps) or "
                           "--preset smoke")

    def check_budget(self, what: str) -> None:
        """A one-line error if a run that learns from labels may ask none (an oracle run needs none). Called
        where the reward source is final: a RAT configuration learns it from the attack's setup."""
        if self.budget == 0 and not self.oracle:
            raise RatError(f"{what} learns from preference labels and the label budget is 0; give --budget > 0, "
                           "or --reward oracle to learn from the true target reward")

    @property
    def schedule(self) -> FeedbackSchedule:
        """Query rounds: the first right after pre-training, then every ``feedback_every`` steps."""
        return FeedbackSchedule(self.budget, self.seed_steps + self.unsupervised_steps, self.feedback_every,
                                self.per_round)


def updates_due(k: int, per_step: float) -> int:
    """SAC updates at the ``k``-th step that learns (k = 0, 1, ...): ``floor(per_step · (k + 1)) − floor(per_step · k)``,
    so any ``k`` steps make ``per_step · k`` updates, rounded down, with no state to save: a resumed run goes on
    exactly where it stopped."""
    return math.floor(per_step * (k + 1)) - math.floor(per_step * k)


class PebbleLearner:
    """The intention policy and everything PEBBLE trains around it.

    Args:
        obs_dim, act_dim: sizes of the environment's observations and actions.
        config: PEBBLE settings.
        store: where labels go (and come back from on resume).
        source: this run's name in the store.
        rng: the run's random generator (segments, queries, batches, teacher noise).
        labeller: who answers the queries; default: a scripted teacher with ``config.teacher``.
        task, target: recorded with every label.
        device: where the networks and batches live.
    """

    def __init__(self, obs_dim: int, act_dim: int, config: PebbleConfig, store: LabelStore, source: str,
                 rng: np.random.Generator, labeller: Labeller | None = None, task: str | None = None,
                 target: str | None = None, device: str | torch.device = "cpu"):
        self.config, self.store, self.source, self.rng, self.device = config, store, source, rng, torch.device(device)
        self.task, self.target = task, target
        self.labeller = labeller or ScriptedTeacher(config.teacher)
        self.agent = SAC(obs_dim, act_dim, config.sac, device=self.device)
        self.buffer = ReplayBuffer(obs_dim, act_dim, config.buffer_capacity)
        self.history = EpisodeHistory(config.max_episodes)
        self.ensemble = RewardEnsemble(obs_dim, act_dim, config.reward).to(self.device)
        self.entropy_stats = RunningMeanStd()
        self.schedule = config.schedule
        self.step = 0  # environment steps observed
        self.asked = 0  # queries counted against the budget
        self.round = 0  # query rounds done
        self.act_dim = act_dim

    @property
    def reward_ready(self) -> bool:
        """Whether the policy's reward carries the target behaviour: r̂ trained at least once
        (before that, stored rewards are 0), or, for an oracle, pre-training over."""
        return self.round > 0 or (self.config.oracle and not self.pretraining)

    @property
    def pretraining(self) -> bool:
        return self.step < self.schedule.first_step

    # --- acting and observing -----------------------------------------------------------------

    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """The intention policy's action (uniform random during the seed steps)."""
        if self.step < self.config.seed_steps and not deterministic:
            return self.rng.uniform(-1.0, 1.0, self.act_dim).astype(np.float32)
        return self.agent.act(obs, deterministic)

    @property
    def wants_physics(self) -> bool:
        """Whether the labeller films segments, so :meth:`observe` needs each step's physics state."""
        return bool(getattr(self.labeller, "films_segments", False))

    def observe(self, obs, action, next_obs, target_reward: float, terminated: bool, truncated: bool,
                physics: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, float]:
        """Take one transition (with its true target reward, for the scripted teacher) and learn.
        ``physics``: the physics state at ``obs`` and its episode's scene, when :attr:`wants_physics`."""
        if self.config.oracle:
            reward = float(target_reward)
        else:
            reward = float(self.learned_reward(obs, action)) if self.reward_ready else 0.0
        self.buffer.add(obs, action, reward, next_obs, terminated)
        self.history.add(obs, action, target_reward, terminated or truncated, physics)
        self.step += 1
        metrics: dict[str, float] = {}
        n = 0 if self.config.oracle else self.schedule.queries_at(self.step, self.asked)
        if n > 0:
            metrics.update(self.query_round(n))
        elif self.config.oracle and self.step == self.schedule.first_step:
            self.reset_critic()  # pre-training is over: forget the intrinsic reward's values, as a labelled run does
        if self.step >= self.config.seed_steps:
            for _ in range(updates_due(self.step - self.config.seed_steps, self.config.updates_per_step)):
                metrics.update(self.update())
        return metrics

    # --- learning ------------------------------------------------------------------------------

    def update(self) -> dict[str, float]:
        """One SAC update: on the intrinsic reward during pre-training, on r̂ afterwards."""
        batch = self.buffer.sample(min(self.config.sac.batch_size, len(self.buffer)), self.rng, self.device)
        if self.pretraining:
            pool = torch.as_tensor(self.buffer.obs[: len(self.buffer)], device=self.device)
            batch["reward"] = state_entropy_reward(batch["obs"], pool, self.entropy_stats, self.config.entropy_k)
        return self.agent.update(batch)

    def segment_return_scale(self) -> float:
        """Mean true target return of a segment in the recent episodes (B-Pref's threshold scale)."""
        L = self.config.segment_length
        return float(np.mean([e[2].sum() * L / len(e[2]) for e in self.history.with_current()]))

    def query_round(self, n: int) -> dict[str, float]:
        """Ask ``n`` queries, train r̂ on every label so far, relabel the buffer.

        If the store already holds this round (it finished before an interruption), its labels
        are used and nothing is stored twice; the round still draws its candidates and asks the
        labeller, so a resumed run consumes random numbers exactly as an uninterrupted one. Labels of
        later rounds (a run resumed from before them) are not read until their round comes.
        """
        cfg = self.config
        candidates = self.history.sample_pairs(n * cfg.candidates_factor, cfg.segment_length, self.rng)
        strategy = cfg.first_strategy if self.round == 0 else cfg.strategy
        labelled = None
        if strategy.startswith("kcenter") and self.store.count(self.source, before_round=self.round):
            labelled = pair_features(self.store.read(self.source, before_round=self.round).pairs)
        chosen = candidates.select(select_queries(strategy, candidates, n, self.ensemble, self.rng, labelled))
        query = QueryRound(self.round, self.step, self.source, self.task, self.target, self.segment_return_scale())
        labels = self.labeller.label(chosen, self.rng, query)
        stored = getattr(self.labeller, "stores_labels", False)  # answered one at a time, into the store itself
        if not stored and self.round not in {r["round"] for r in self.store.rounds(self.source)}:
            self.store.add(chosen.select(labels.index), labels.y, self.labeller.describe(), self.source,
                           round=self.round, task=self.task, target=self.target, step=self.step, asked=n)
        self.asked += n
        first = self.round == 0
        self.round += 1
        metrics = self.train_reward()
        metrics.update({"labels": float(self.store.count(self.source, before_round=self.round)), "queries_asked": float(self.asked),
                        "round_labels": float(len(labels.y)), "round_ties": float(np.sum(labels.y == 0.5))})
        metrics.update(self.reward_agreement())
        if first:
            self.reset_critic()
        return metrics

    def reward_agreement(self, episodes: int = 20) -> dict[str, float]:
        """r̂ against the target's own reward over the last ``episodes`` episodes (a diagnostic, logged after
        every round as ``reward_step_corr``, ``reward_segment_corr`` and ``reward_pairs_ordered``; see
        :func:`~rat.preferences.reward_model.reward_agreement`). It reads the target's reward, which the
        scripted teacher labels by and another labeller may not."""
        L = self.config.segment_length
        recent = [e[:3] for e in self.history.with_current()[-episodes:] if len(e[0]) >= L]
        if not recent:
            return {}
        obs, act, true = (np.concatenate([part[: len(part) // L * L] for part in parts]) for parts in zip(*recent))
        scores = reward_agreement(self.ensemble.r_hat(obs, act), true, L)
        return {f"reward_{name}": value for name, value in scores.items()}

    def reset_critic(self) -> None:
        """PEBBLE's critic reset at the end of pre-training, then ``reset_updates`` SAC updates on the new reward."""
        self.agent.reset_critic()
        for _ in range(self.config.reset_updates):
            self.update()

    def train_reward(self) -> dict[str, float]:
        """Train the ensemble on every label of this run's rounds so far, then relabel the whole replay buffer."""
        labels = self.store.read(self.source, before_round=self.round)
        if len(labels) == 0:
            return {}
        p = labels.pairs
        metrics = self.ensemble.train_round(p.obs0, p.act0, p.obs1, p.act1, labels.y, self.rng)
        self.buffer.relabel(lambda o, a, _: self.learned_reward(o, a))
        return metrics

    def learned_reward(self, obs: np.ndarray, action: np.ndarray) -> np.ndarray:
        """r̂ as the policy is trained on it: the ensemble's mean."""
        return self.ensemble.r_hat(obs, action)

    # --- checkpoints ----------------------------------------------------------------------------

    def state_dict(self) -> dict:
        return {
            "agent": self.agent.state_dict(), "agent_optimizers": self.agent.optimizer_state(),
            "ensemble": self.ensemble.state_dict(), "ensemble_optimizers": self.ensemble.optimizer_state(),
            "buffer": self.buffer.state_dict(), "history": self.history.state_dict(),
            "entropy_stats": self.entropy_stats.state_dict(),
            "counters": {"step": self.step, "asked": self.asked, "round": self.round},
        }

    def checkpoint_meta(self) -> dict:
        """What a checkpoint keeps beside the tensors: the name this run's labels carry in its store."""
        return {"label_source": self.source}

    def restore_meta(self, meta: dict) -> None:
        """Read the labels under the name they were asked by (:meth:`checkpoint_meta`), so a run moved or copied
        to another directory resumes with its own labels rather than asking them again."""
        self.source = meta["label_source"]

    def load_state_dict(self, state: dict) -> None:
        self.agent.load_state_dict(state["agent"])
        self.agent.load_optimizer_state(state["agent_optimizers"])
        self.ensemble.load_state_dict(state["ensemble"])
        self.ensemble.load_optimizer_state(state["ensemble_optimizers"])
        self.buffer.load_state_dict(state["buffer"])
        self.history.load_state_dict(state["history"])
        self.entropy_stats.load_state_dict(state["entropy_stats"])
        c = state["counters"]
        self.step, self.asked, self.round = int(c["step"]), int(c["asked"]), int(c["round"])
