"""Robust training: a SAC agent and an adversary in alternating phases, on the project's training loop.

One trainer serves every method (:data:`METHODS`). What differs is the adversary (RAT's, SA-RL's or PA-AD's,
or none) and the term added to the agent's actor loss (:mod:`rat.robust.terms`):

1. **Critic warm-up** (``init="finetune"``): the agent starts from the victim's actor; the zoo ships actors
   alone, so the critic first learns from ``critic_warmup`` clean steps of that actor (its actions perturbed by
   ``warmup_noise``), the actor frozen. Afterwards the actor's loss keeps an :class:`~rat.robust.terms.Anchor` to
   the starting actor and the temperature stays at ``finetune_temperature`` (docs/robust.md says why).
   ``init="scratch"``: a fresh agent, ``random_steps`` uniform actions first.
2. **Phase 0**: the adversary trains ``first_adversary_steps`` against the frozen starting agent.
3. Then, until the agent has made ``agent_steps`` steps: an **agent phase** (SAC on the task reward; every
   observation perturbed by the frozen adversary, the buffer storing s̃ₜ and s̃ₜ₊₁ exactly as the agent saw
   them), the agent's weights copied into the frozen victim in place, and an **adversary phase** (the adversary
   *continues*: RAT's π_θ, r̂, labels and buffer carry over; PPO continues its rollouts).

Every phase ends at the first episode end at or after its length, so a checkpoint (taken at episode ends)
finds every environment between episodes, and a killed run resumes exactly where it was.

RAT-WocaR has no adversary phases: after phase 0 (the RAT attack whose intention critic it needs) the agent
trains on clean observations with κ·Q_φ^targ(s, ã) added (the release's term); with ``wocar_critic="worst-case"``
it needs no attacker at all, and learns a worst-attack Q_w beside SAC (:class:`~rat.robust.terms.WorstCaseValue`).
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field, replace
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from rat import seeds
from rat.agents.buffer import ReplayBuffer
from rat.agents.networks import TanhGaussianActor
from rat.agents.sac import SAC, SACConfig
from rat.attacks.base import AttackSetup
from rat.attacks.evaluation import evaluate_attack
from rat.attacks.threat import AttackedObservation
from rat.device import resolve_device
from rat.errors import RatError
from rat.eval import evaluate
from rat.robust.adversaries import PhaseAdversary
from rat.robust.terms import Anchor, IntentionValue, WorstCaseValue, kappa_at, state_smoothness
from rat.runs import restore_rng_state, rng_state
from rat.victims.base import ModuleVictim

METHODS = {
    "rat-atla": "RAT's adversary (preference labels, a target behaviour) alternating with the agent (the paper's RAT-ATLA)",
    "rat-wocar": "the agent trained clean with a worst-case term: the intention policy's critic (the release's) or a "
                 "worst-attack Q of the task reward (WocaR's)",
    "atla": "SA-RL's PPO adversary alternating with the agent (ATLA, with a SAC agent)",
    "pa-atla": "PA-AD's PPO director and gradient actor alternating with the agent (PA-ATLA, with a SAC agent)",
    "none": "no defence: SAC on clean observations alone (the control: what the same training does without one)",
}
ADVERSARY_OF = {"rat-atla": "rat", "rat-wocar": "rat", "atla": "sa-rl", "pa-atla": "pa-ad"}  #: the attack each trains against
PHASES = ("warm-up", "adversary", "agent", "done")


@dataclass(frozen=True)
class RobustConfig:
    """How to train one robust agent (defaults for a 2-core CPU; the originals' lengths are out of reach here)."""

    method: str = "rat-atla"  #: one of ``METHODS``
    init: str = "finetune"  #: finetune (start from the victim's actor) or scratch (a fresh agent)
    agent_steps: int = 40_000  #: the agent's environment steps after its warm-up, over all its phases
    phase_steps: int = 2_000  #: length of each agent phase (ATLA: 2,048); ends at the next episode end
    adversary_phase_steps: int = 2_000  #: length of each adversary phase after phase 0
    first_adversary_steps: int = 50_000  #: phase 0, the adversary against the starting agent (RAT's cpu preset)
    critic_warmup: int = 10_000  #: finetune: clean steps of the starting actor, critic-only updates
    warmup_updates: int = 6  #: finetune: critic updates per warm-up step (Q must near the actor's value first)
    #: finetune: σ of the Gaussian noise on the starting actor's warm-up actions, so that the critic learns Q
    #: around the actor's actions and not only on them (the zoo's actors are near-deterministic)
    warmup_noise: float = 0.3
    #: finetune: weight of ‖ã − μ₀(s)‖² in the actor's loss, μ₀ the starting actor at the true observation s
    #: (ã drawn at the perturbed s̃), in units of the critic's mean |Q| (TD3+BC's scale, 1/2.5); 0: off.
    #: Without it the first actor updates lose the task (docs/robust.md)
    anchor: float = 0.4
    #: finetune: the agent's entropy temperature, fixed (the zoo's actors sit far below SAC's target entropy,
    #: and a learnt temperature would widen them); 0: SAC's own, learnt from sac.init_temperature
    finetune_temperature: float = 0.001
    random_steps: int = 5_000  #: scratch: uniform random actions first
    adversary_sample: bool = True  #: the agent's phases see Δ sampled from the adversary (ATLA's), else its mean
    adversary_reward: str = "target"  #: atla, pa-atla: the PPO adversary's reward, the target's or neg-task (ATLA's −r)
    wocar_critic: str = "intention"  #: rat-wocar: intention (the release's term) or worst-case (WocaR's estimate)
    wocar_kappa: float = 0.5  #: rat-wocar: κ of the worst-case term (the release's 0.5)
    wocar_schedule: str = "constant"  #: rat-wocar: κ constant (the release's) or linear from 0 (WocaR's)
    worst_case_steps: int = 10  #: worst-case: signed-gradient steps on Δ to find the worst observation
    state_reg: float = 0.0  #: weight of SA-PPO's state regulariser on the agent (PA-ATLA's release uses one); 0: off
    sac: SACConfig = field(default_factory=lambda: SACConfig(lr=1e-4, batch_size=256))  #: the agent's SAC
    buffer_capacity: int = 1_000_000  #: the agent's replay buffer
    eval_every: int = 10_000  #: environment steps (agent and adversary) between evaluations
    eval_episodes: int = 10  #: episodes of each evaluation (clean, and under the adversary)
    final_eval_episodes: int = 100  #: the paper's table 3 runs 100
    checkpoint_every: int = 5_000  #: environment steps between checkpoints (at the next episode end)
    seed: int = 0
    device: str = "cpu"  #: auto, cpu or cuda

    def __post_init__(self):
        if self.method not in METHODS:
            raise RatError(f"unknown robust-training method '{self.method}'; use one of: {', '.join(METHODS)}")
        choices = {"init": ("finetune", "scratch"), "adversary_reward": ("target", "neg-task"),
                   "wocar_critic": ("intention", "worst-case"), "wocar_schedule": ("constant", "linear")}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise RatError(f"{name.replace('_', '-')} must be one of {', '.join(allowed)}, got '{getattr(self, name)}'")
        for name in ("agent_steps", "phase_steps", "adversary_phase_steps", "eval_every", "eval_episodes",
                     "final_eval_episodes", "checkpoint_every", "worst_case_steps", "warmup_updates"):
            if getattr(self, name) <= 0:
                raise RatError(f"{name.replace('_', '-')} must be positive, got {getattr(self, name)}")
        for name in ("first_adversary_steps", "critic_warmup", "random_steps", "wocar_kappa", "state_reg",
                     "warmup_noise", "anchor", "finetune_temperature"):
            if getattr(self, name) < 0:
                raise RatError(f"{name.replace('_', '-')} must not be negative, got {getattr(self, name)}")
        if self.needs_adversary and self.first_adversary_steps == 0:
            raise RatError(f"{self.method} needs an adversary trained first: give first-adversary-steps > 0")

    def agent_sac(self) -> SACConfig:
        """The agent's SAC settings: ``sac``, its temperature fixed at ``finetune_temperature`` when fine-tuning."""
        if self.init == "finetune" and self.finetune_temperature > 0:
            return replace(self.sac, learnable_temperature=False, init_temperature=self.finetune_temperature)
        return self.sac

    @property
    def alternates(self) -> bool:
        """Whether adversary phases follow the agent's (every method with an adversary but RAT-WocaR)."""
        return self.method in ADVERSARY_OF and self.method != "rat-wocar"

    @property
    def needs_adversary(self) -> bool:
        return self.method in ADVERSARY_OF and (self.method != "rat-wocar" or self.wocar_critic == "intention")

    @property
    def adversary_method(self) -> str | None:
        return ADVERSARY_OF[self.method] if self.needs_adversary else None


#: ``--preset smoke``: every phase once or twice, in minutes (a check that a task runs, not a result)
SMOKE = dict(agent_steps=2_000, phase_steps=1_000, adversary_phase_steps=1_000, first_adversary_steps=2_000,
             critic_warmup=1_000, random_steps=1_000, eval_every=2_000, eval_episodes=2, final_eval_episodes=5,
             checkpoint_every=1_000)


def robust_preset(preset: str, **overrides) -> RobustConfig:
    """:class:`RobustConfig` under a named preset: ``cpu`` (its defaults) or ``smoke``, with field overrides."""
    if preset not in ("cpu", "smoke"):
        raise RatError(f"unknown robust-training preset '{preset}'; use cpu or smoke")
    return RobustConfig(**(SMOKE if preset == "smoke" else {}) | overrides)


class TaskReward(gym.Wrapper):
    """Records the environment's own reward in ``info["task_reward"]`` (ATLA's adversary is paid −r)."""

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, dict(info, task_reward=float(reward))


def neg_task_reward(obs, action, next_obs, info) -> float:
    """ATLA's adversary reward: minus the victim's task reward."""
    return -float(info["task_reward"])


class RobustTrainer:
    """A robust agent and its adversary, one unit at a time (a :class:`~rat.loop.Trainer`).

    A unit is one environment step of the agent, one of RAT's, or one PPO rollout. ``step`` counts the
    environment steps of both.

    Args:
        config: the robust-training settings.
        setup: the attack's setup; its victim is the frozen copy of the agent the adversary trains against
            (its weights are replaced in place at each agent phase's end).
        agent_env: the agent's own task, with its task reward.
        adversary: the adversary (None for RAT-WocaR's worst-case form).
        actor: the starting actor (``init="finetune"``), or None.
    """

    kind = "robust-run"

    def __init__(self, config: RobustConfig, setup: AttackSetup, agent_env: gym.Env,
                 adversary: PhaseAdversary | None, actor: TanhGaussianActor | None):
        cfg = self.config = config
        if not isinstance(setup.victim, ModuleVictim):
            raise RatError("robust training swaps the agent's weights into its victim: it needs a victim made by "
                           "rat.robust.train_robust (a ModuleVictim)")
        self.setup, self.victim, self.target, self.threat = setup, setup.victim, setup.target, setup.threat
        self.device = resolve_device(cfg.device)
        self.rng = np.random.default_rng(cfg.seed + seeds.ROBUST)
        obs_dim, act_dim = agent_env.observation_space.shape[0], agent_env.action_space.shape[0]
        self.agent = SAC(obs_dim, act_dim, cfg.agent_sac(), device=self.device)
        if actor is not None:
            self.agent.actor.load_state_dict(actor.state_dict())
        self.victim.load_policy(self.agent.actor.state_dict())  # phase 0's adversary trains against the starting agent
        self.buffer = ReplayBuffer(obs_dim, act_dim, cfg.buffer_capacity)
        self.true_obs = np.zeros_like(self.buffer.obs)  # beside the buffer, row for row: s under each stored s̃
        self.adversary = adversary
        self.env = AttackedObservation(agent_env, self._shown_delta, self.threat)
        self.term = None  # the agent's extra actor-loss term (RAT-WocaR)
        if cfg.method == "rat-wocar" and cfg.wocar_critic == "worst-case" and cfg.wocar_kappa > 0:
            self.term = WorstCaseValue(obs_dim, act_dim, self.threat, cfg.sac.hidden, cfg.sac.layers, cfg.sac.lr,
                                       cfg.sac.gamma, cfg.sac.tau, cfg.worst_case_steps).to(self.device)
        self.regulariser = state_smoothness(self.agent.actor, self.threat, cfg.state_reg) if cfg.state_reg else None
        self.anchor = None  # ‖ã − μ₀(s)‖², μ₀ the frozen starting actor
        if cfg.anchor and actor is not None:
            self.anchor = Anchor(copy.deepcopy(actor).to(self.device), self.agent.critic, cfg.anchor)
        self.phase = "warm-up" if (cfg.init == "finetune" and cfg.critic_warmup) or cfg.init == "scratch" else "adversary"
        if self.phase == "adversary" and adversary is None:
            self.phase = "agent"
        self.phase_start = 0  # the phase's own step counter when it began (agent or adversary steps)
        self.agent_steps, self.warmup_steps, self.rounds = 0, 0, 0
        self.counters = {"agent_updates": 0, "adversary_phases": 0, "agent_phases": 0}
        self.obs: np.ndarray | None = None
        self.delta: Any = None  # the frozen adversary's obs -> Δ during an agent phase
        self.metrics: dict[str, float] = {}
        self.finished = False
        self.t0 = time.perf_counter()

    # --- what the agent is shown -------------------------------------------------------------------

    def _shown_delta(self, obs: np.ndarray) -> np.ndarray:
        """Δ of the observation the agent sees: the frozen adversary's in an agent phase, none otherwise."""
        if self.delta is None:
            return np.zeros_like(obs, dtype=np.float64)
        return self.delta(obs)

    @property
    def step(self) -> int:
        return self.warmup_steps + self.agent_steps + (self.adversary.step if self.adversary is not None else 0)

    @property
    def perturbs(self) -> bool:
        """Whether the agent's phases see the adversary's perturbations (not RAT-WocaR: it trains clean)."""
        return self.adversary is not None and self.config.alternates

    # --- the phases ---------------------------------------------------------------------------------

    def advance(self) -> dict[str, float] | None:
        if self.phase == "adversary":
            metrics = self.adversary.advance()
            if metrics is not None and self.adversary.step - self.phase_start >= self._adversary_length():
                self._begin("agent")
            return metrics
        return self._agent_step()

    def _adversary_length(self) -> int:
        cfg = self.config
        return cfg.first_adversary_steps if self.counters["adversary_phases"] == 0 else cfg.adversary_phase_steps

    def _begin(self, phase: str) -> None:
        cfg = self.config
        if self.phase == "adversary":
            self.counters["adversary_phases"] += 1
            if cfg.method == "rat-wocar":  # phase 0 made the intention policy whose critic the term uses
                self.term = IntentionValue(self.adversary.trainer.learner.agent.critic_target)
        elif self.phase == "agent":
            self.counters["agent_phases"] += 1
            self.victim.load_policy(self.agent.actor.state_dict())  # the adversary now trains against this agent
        phase_zero = self.counters["adversary_phases"] == 0
        if phase == "adversary" and (self.adversary is None or not (cfg.alternates or phase_zero)):
            phase = "agent"  # no adversary phase here: the agent goes on (or is done)
        if phase == "agent" and self.agent_steps >= cfg.agent_steps:
            phase = "done"
        self.phase = phase
        if phase == "done":
            self.finished = True
            self.delta = None
        elif phase == "agent":
            self.phase_start = self.agent_steps
            self.delta = self.adversary.perturbation(cfg.adversary_sample) if self.perturbs else None
        elif phase == "adversary":
            self.phase_start = self.adversary.step
            self.delta = None

    def _act(self, obs: np.ndarray) -> np.ndarray:
        cfg = self.config
        if self.phase == "warm-up" and cfg.init == "scratch":
            return self.env.action_space.sample()
        action = self.agent.act(obs)
        if self.phase == "warm-up" and cfg.warmup_noise:
            action = np.clip(action + cfg.warmup_noise * self.rng.standard_normal(action.shape), -1.0, 1.0)
        return action

    def _agent_step(self) -> dict[str, float] | None:
        cfg = self.config
        if self.obs is None:
            self.obs, info = self.env.reset(seed=int(self.rng.integers(2**31)))
            self.true = info["true_obs"]
            self.ep_return, self.succeeded, self.target_hit = 0.0, False, False
            self.target_test = self.target.episode_success()
        seen = self.obs
        action = self._act(seen)
        next_seen, reward, terminated, truncated, info = self.env.step(action)
        self.buffer.add(seen, action, reward, next_seen, terminated)  # s̃ₜ and s̃ₜ₊₁, as the agent saw them
        self.true_obs[self.buffer.last_index] = self.true
        self.ep_return += reward
        self.succeeded |= bool(info.get("success", False))
        self.target_hit |= self.target_test(info)
        self.obs, self.true = next_seen, info["true_obs"]
        warm = self.phase == "warm-up"
        if warm:
            self.warmup_steps += 1
        else:
            self.agent_steps += 1
        if len(self.buffer) >= cfg.sac.batch_size:
            for _ in range(cfg.warmup_updates if warm and cfg.init == "finetune" else 1):
                self._update(actor=not warm)
        if not (terminated or truncated):
            return None
        self.obs = None
        out = {"episode_return": self.ep_return, "episode_success": float(self.succeeded),
               "episode_target_success": float(self.target_hit), "attacked": float(self.delta is not None),
               **self.metrics}
        if warm and self.warmup_steps >= (cfg.critic_warmup if cfg.init == "finetune" else cfg.random_steps):
            self._begin("adversary")  # warm-up over: phase 0 of the adversary, or the agent's first phase
        elif not warm and (self.agent_steps - self.phase_start >= cfg.phase_steps or self.agent_steps >= cfg.agent_steps):
            self._begin("adversary")
        return out

    def _extra(self, batch: dict[str, torch.Tensor]):
        terms = [t for t in (self.term, self.regulariser) if t is not None]
        if self.anchor is not None:
            terms.append(lambda obs, action: self.anchor(obs, action, batch["true_obs"]))
        if not terms:
            return None
        if self.term is not None:
            self.term.kappa = kappa_at(self.config.wocar_kappa, self.config.wocar_schedule,
                                       self.agent_steps / self.config.agent_steps)
        return lambda obs, action: sum(t(obs, action) for t in terms)

    def _update(self, actor: bool) -> None:
        idx = self.buffer.sample_indices(self.config.sac.batch_size, self.rng)
        batch = self.buffer.take(idx, self.device) | {"true_obs": torch.as_tensor(self.true_obs[idx], device=self.device)}
        if isinstance(self.term, WorstCaseValue):
            self.metrics.update(self.term.update(batch, self.agent.actor))
        self.metrics.update(self.agent.update(batch, actor=actor, actor_extra=self._extra(batch) if actor else None))
        self.counters["agent_updates"] += int(actor)

    # --- evaluation ---------------------------------------------------------------------------------

    def current_agent(self) -> ModuleVictim:
        """The agent as it is now, frozen, as a victim (a copy: training goes on)."""
        return ModuleVictim(copy.deepcopy(self.agent.actor).cpu(), self.victim.observation_space,
                            self.victim.action_space, name="robust-agent", meta=dict(self.victim.meta))

    def evaluate_agent(self, episodes: int, seed: int) -> dict[str, float]:
        """The agent's clean task return and success, and under the adversary as it is (its mean Δ)."""
        agent, s = self.current_agent(), self.setup
        clean = evaluate(lambda o: agent.act(torch.as_tensor(o, dtype=torch.float32).unsqueeze(0)).squeeze(0).numpy(),
                         s.make_env(self.config.seed + seeds.EVAL_ENV), episodes, seed, target=self.target)
        out = {"eval_clean_return": clean.mean_return, "eval_clean_target_success": clean.success_rate}
        if self.adversary is not None and self.phase != "warm-up":
            attacked = evaluate_attack(agent, self.adversary.perturbation(sample=False),
                                       s.make_env(self.config.seed + seeds.EVAL_ENV), self.target, self.threat,
                                       episodes, seed)
            out |= {"eval_attacked_return": attacked.result.mean_return,
                    "eval_success_rate": attacked.result.success_rate}  # the adversary's target success
        return out

    def evaluate(self) -> dict[str, float]:
        return self.evaluate_agent(self.config.eval_episodes, seeds.periodic(self.step)) | {
            **self.counters, "agent_steps": float(self.agent_steps)}

    # --- state --------------------------------------------------------------------------------------

    def state_dict(self) -> dict:
        state = {"agent": self.agent.state_dict(), "optimizers": self.agent.optimizer_state(),
                 "buffer": self.buffer.state_dict(), "true_obs": self.true_obs[:len(self.buffer)],
                 "rng": rng_state(self.rng),
                 "victim": self.victim.policy.state_dict()}
        if self.adversary is not None:
            state["adversary"] = self.adversary.state_dict()
        if isinstance(self.term, WorstCaseValue):
            state["worst_case"] = {"nets": self.term.state_dict(), "optimizer": self.term.optimizer_state()}
        elif isinstance(self.term, IntentionValue):
            state["intention_critic"] = self.term.state_dict()
        return state

    def load_state_dict(self, state: dict, meta: dict) -> None:
        self.agent.load_state_dict(state["agent"])
        self.agent.load_optimizer_state(state["optimizers"])
        self.buffer.load_state_dict(state["buffer"])
        self.true_obs[:len(self.buffer)] = state["true_obs"]
        self.victim.load_policy(state["victim"])
        if self.adversary is not None:
            self.adversary.load_state_dict(state["adversary"], meta.get("adversary_meta", {}) | {
                "adversary_step": meta["adversary_step"]})
        if "worst_case" in state:
            self.term.load_state_dict(state["worst_case"]["nets"])
            self.term.optimizer.load_state_dict(state["worst_case"]["optimizer"])
        if "intention_critic" in state:
            self.term = IntentionValue(self.adversary.trainer.learner.agent.critic_target)
            self.term.load_state_dict(state["intention_critic"])
        restore_rng_state(self.rng, state["rng"])  # last: loading the adversary's state restores its own streams
        self.phase, self.phase_start = meta["phase"], int(meta["phase_start"])
        self.agent_steps, self.warmup_steps = int(meta["agent_steps"]), int(meta["warmup_steps"])
        self.counters.update({k: int(meta["counters"][k]) for k in self.counters})
        self.finished = self.phase == "done"
        self.delta = self.adversary.perturbation(self.config.adversary_sample) \
            if self.phase == "agent" and self.perturbs else None

    def checkpoint_meta(self) -> dict:
        return {"phase": self.phase, "phase_start": self.phase_start, "agent_steps": self.agent_steps,
                "warmup_steps": self.warmup_steps, "counters": dict(self.counters),
                "adversary_step": self.adversary.step if self.adversary is not None else 0,
                "adversary_meta": self.adversary.checkpoint_meta() if self.adversary is not None else {}}

    def planned_steps(self, horizon: int, adversary_unit: int = 1) -> int:
        """The run's environment steps if every episode lasts ``horizon`` steps (the progress bar's total);
        ``adversary_unit``: the steps of one adversary unit (a PPO rollout's), whose phases end on whole units."""
        cfg = self.config
        whole = lambda n, unit=horizon: -(-n // unit) * unit  # noqa: E731 (phases end at episode ends)
        warm = whole(cfg.critic_warmup if cfg.init == "finetune" else cfg.random_steps)
        rounds = -(-cfg.agent_steps // whole(cfg.phase_steps))
        adversary = 0
        if self.adversary is not None:
            unit = adversary_unit if adversary_unit > 1 else horizon
            adversary = whole(cfg.first_adversary_steps, unit)
            adversary += rounds * whole(cfg.adversary_phase_steps, unit) * cfg.alternates  # one after each agent phase
        return warm + min(rounds * whole(cfg.phase_steps), whole(cfg.agent_steps)) + adversary
