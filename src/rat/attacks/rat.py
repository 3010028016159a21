"""RAT: the adversary learns to make the perturbed victim behave like an intention policy that
PEBBLE learns from preference labels, with a weighting network re-weighting states by a
bi-level, one-step-lookahead update, on data from the combined behaviour policy.

:func:`train_rat` is the whole algorithm (the paper's Algorithm 1) in one loop. It takes any
gymnasium environment factory, any :class:`~rat.victims.Victim` and any target behaviour.

Ablations (the paper's table 4), by ``RATConfig.ablation``:

- ``"no-weighting"``: h_ω ≡ 1 and no outer updates (plain KL imitation);
- ``"no-combined"``: data is collected by the intention policy alone (PEBBLE's own collection),
  never by the perturbed victim;
- ``"no-intention"``: no policy to imitate: the adversary directly minimises the outer loss,
  i.e. maximises the intention critic's value Q_φ(s, μ_ν(s̃)) of the perturbed victim's action,
  data comes from the perturbed victim alone, and the weighting network is off (its objective is
  defined through the imitation step). π_θ still exists only as the critic's bootstrap policy.

Sequence victims (Decision Transformers): the victim's context follows each episode as it
happened — the observation as perturbed, the action taken (π_θ's, after the combined behaviour
policy's switch), the environment's reward — and every stored state keeps the context the victim
had there, packed beside the replay buffer, so the adversary trains on states *in their context*.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field, replace
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from rat import seeds
from rat.attacks.base import SNAPSHOT, AttackSetup, register_attack
from rat.attacks.evaluation import AttackEval, evaluate_attack
from rat.attacks.losses import (
    Adversary,
    Imitation,
    WeightingNetwork,
    hypergradient,
    inner_loss,
    saturation,
)
from rat.attacks.refine import REFINE_SWITCH_GAP, check_refine_loss, refined_function
from rat.attacks.runs import conclude
from rat.attacks.saved import (
    IntentionPolicy,
    adversary_function,
    load_rat_attack,
    policy_learned_return,
    select_by_learned_reward,
)
from rat.attacks.threat import Perturbation, ThreatModel
from rat.checkpoint import save_checkpoint
from rat.device import resolve_device
from rat.envs.physics import physics_of
from rat.envs.tasks import episode_length
from rat.errors import RatError
from rat.loop import TrainingLoop
from rat.plots import plot_training
from rat.preferences.labeller import Labeller
from rat.preferences.pebble import PebbleConfig, PebbleLearner
from rat.preferences.store import LabelStore
from rat.reports import AttackReport
from rat.runs import Run, restore_rng_state, rng_state, seed_everything, to_jsonable
from rat.victims.base import Victim, VictimPolicy, check_compatible, is_sequence

ABLATIONS = ("none", "no-weighting", "no-combined", "no-intention")
@dataclass(frozen=True)
class RATConfig:
    """A RAT attack (defaults: the paper's, with the released schedule of ``docs/design.md`` §5)."""

    epsilon: float = 0.1  #: budget, raw observation units
    norm: str = "linf"  #: linf, l2, l1 or l1-rescale
    seed: int = 0  #: seeds everything
    total_steps: int = 100_000  #: environment steps
    pebble: PebbleConfig = field(default_factory=PebbleConfig)  #: intention policy and labels
    adversary_hidden: int = 256  #: adversary width (3 hidden layers)
    adversary_lr: float = 3e-4  #: Adam learning rate of the adversary; also η of the virtual step
    adversary_every: int = 100  #: environment steps between adversary phases
    adversary_updates: int = 10  #: adversary updates per phase
    adversary_batch: int = 1024  #: states per adversary / weighting update
    weighting_every: int = 1000  #: environment steps between weighting updates (2000 for opposite behaviours)
    weighting_lr: float = 1e-3  #: Adam learning rate of the weighting network
    victim_std: float = 1.0  #: σ_v of the perturbed policy N(μ_ν(s̃), σ_v²)
    kl_form: str = "exact"  #: "exact" Gaussian KL, or "released"
    hypergradient: str = "exact"  #: "exact" per-state hypergradient, or "batch-mean" (released)
    ablation: str = "none"  #: none, no-weighting, no-combined, no-intention
    horizon: int | None = None  #: episode length H of the combined behaviour policy's switch (None: the env's time limit)
    eval_every: int = 10_000  #: steps between attack evaluations
    eval_episodes: int = 10  #: episodes per evaluation during training
    final_eval_episodes: int = 30  #: episodes of the final evaluation (the paper's 30)
    select: str = "last"  #: "last" adversary (the paper's), or the snapshot whose attack scores best under r̂ ("reward")
    imitate: str = "current"  #: the adversary imitates the "current" π_θ (the paper's), or the "best" so far under r̂ (kept from the first evaluation after π_θ learns from r̂)
    imitate_episodes: int = 3  #: π_θ's episodes per evaluation that score it under r̂ (imitate="best")
    checkpoint_every: int = 10_000  #: a checkpoint at the first episode end after this many steps
    refine_steps: int = 0  #: Adam steps on Δ per observation towards π_θ's action, when attacking (0: the network's Δ)
    refine_lr: float = 0.1  #: their learning rate (on Δ before tanh)
    refine_loss: str = "l2"  #: what they minimise: "l2", the squared action gap; "q", −Q_φ; "l2-or-q": l2, and −Q_φ where l2 leaves a gap above refine_switch_gap
    refine_switch_gap: float = REFINE_SWITCH_GAP  #: refine_loss="l2-or-q": the gap ‖μ_ν(s̃) − tanh μ_θ(s)‖ above which an observation is refined by −Q_φ
    device: str = "auto"  #: auto (a GPU when torch sees one), cpu or cuda

    def __post_init__(self):
        _ = self.threat  # validates epsilon and norm
        if self.ablation not in ABLATIONS:
            raise RatError(f"unknown ablation '{self.ablation}'; use one of: {', '.join(ABLATIONS)}")
        if self.select not in ("last", "reward"):
            raise RatError(f"select must be last or reward, got '{self.select}'")
        if self.imitate not in ("current", "best") or self.imitate_episodes <= 0:
            raise RatError(f"imitate must be current or best (with imitate-episodes > 0), got '{self.imitate}'")
        if self.imitate == "best" and self.pebble.oracle:
            raise RatError("imitate=best scores π_θ with r̂, which an oracle run does not learn; use imitate=current")
        if self.select == "reward" and self.pebble.oracle:
            raise RatError("select=reward scores snapshots with r̂, which an oracle run does not learn; use select=last")
        if self.kl_form not in ("exact", "released") or self.hypergradient not in ("exact", "batch-mean"):
            raise RatError("kl-form must be exact or released, hypergradient exact or batch-mean")
        check_refine_loss(self.refine_loss)
        if self.refine_switch_gap < 0:
            raise RatError(f"refine-switch-gap must be ≥ 0, got {self.refine_switch_gap}")
        if self.refine_steps < 0 or self.refine_lr <= 0:
            raise RatError(f"refine-steps must be ≥ 0 and refine-lr positive, got {self.refine_steps} and {self.refine_lr}")
        if self.refine_steps and self.ablation == "no-intention":
            raise RatError("refine-steps refines Δ towards π_θ, which the no-intention ablation does not imitate; "
                           "drop one of the two")
        for name in ("total_steps", "adversary_every", "adversary_updates", "adversary_batch", "weighting_every",
                     "eval_every", "eval_episodes", "final_eval_episodes", "checkpoint_every"):
            if getattr(self, name) <= 0:
                raise RatError(f"{name.replace('_', '-')} must be positive, got {getattr(self, name)}")
        if self.horizon is not None and self.horizon <= 0:
            raise RatError(f"horizon must be positive, got {self.horizon}")
        self.pebble.check_steps(self.total_steps, "RAT")  # the adversary starts at the first query round

    @property
    def threat(self) -> ThreatModel:
        return ThreatModel(self.epsilon, self.norm)


class CombinedBehaviourPolicy:
    """Who acts at each episode step: the perturbed victim before a switch step h, π_θ from h on.

    h ~ U{0, …, H−1} is drawn at every episode start (``"combined"``); ``"intention"`` and
    ``"victim"`` fix h = 0 and h = H.
    """

    def __init__(self, horizon: int, mode: str = "combined"):
        self.horizon, self.mode, self.switch = horizon, mode, 0

    def start_episode(self, rng: np.random.Generator) -> None:
        if self.mode == "combined":
            self.switch = int(rng.integers(0, self.horizon))
        else:
            self.switch = {"intention": 0, "victim": self.horizon}[self.mode]

    def victim_acts(self, episode_step: int) -> bool:
        return episode_step < self.switch


def adversary_update(adversary: Adversary, optimizer: torch.optim.Optimizer, weighting: WeightingNetwork | None,
                     objective: Imitation, obs: torch.Tensor, ablation: str = "none", context=None) -> dict[str, float]:
    """One inner-level step: only the adversary's parameters receive a gradient and change.

    Minimises the weighted KL to the intention policy (weights 1 without a weighting network), or, for the
    ``no-intention`` ablation, the outer loss itself.
    ``context``: a sequence victim's, per state.
    """
    noise = torch.randn_like(obs)
    if ablation == "no-intention":
        loss = objective.outer(adversary, None, obs, noise, context)
    else:
        with torch.no_grad():
            weights = weighting(obs) if weighting is not None else torch.ones(len(obs), device=obs.device)
        loss = inner_loss(weights, objective.kl(adversary, None, obs, noise, context))
    optimizer.zero_grad(set_to_none=True)
    loss.backward(inputs=list(adversary.parameters()))  # nothing else may accumulate a gradient
    optimizer.step()
    return {"adversary_loss": loss.item()}


def weighting_update(weighting: WeightingNetwork, optimizer: torch.optim.Optimizer, adversary: Adversary,
                     objective: Imitation, obs_inner: torch.Tensor, obs_outer: torch.Tensor, inner_lr: float,
                     form: str = "exact", context_inner=None, context_outer=None) -> dict[str, float]:
    """One outer-level step: the hypergradient moves the weighting network, and nothing else."""
    grads = hypergradient(objective, adversary, weighting, obs_inner, torch.randn_like(obs_inner), obs_outer,
                          torch.randn_like(obs_outer), inner_lr, form, context_inner, context_outer)
    optimizer.zero_grad(set_to_none=True)
    for p, g in zip(weighting.parameters(), grads):
        p.grad = None if g is None else g.detach()
    optimizer.step()
    with torch.no_grad():
        w = weighting(obs_inner)
    return {"weight_mean": w.mean().item(), "weight_std": w.std().item()}


class RATTrainer:
    """The whole state of a RAT run, one environment step at a time (a :class:`~rat.loop.Trainer`).

    Owns the intention policy and its learner (PEBBLE), the adversary, the weighting network,
    their optimisers, the combined behaviour policy and the run's random generator, so a
    profiler or a robust-training loop can step it and look inside.

    Args:
        config: the attack's settings.
        setup: victim, target, environments, threat model, labeller.
        env: the training environment (made by ``setup.make_env(config.seed)``).
        store: where labels go; source: this run's name in it.
        snapshots: the folder of the adversary snapshots taken at every evaluation.
        labeller: who answers preference queries (default: the scripted teacher of ``config.pebble``).
    """

    kind = "rat-run"

    def __init__(self, config: RATConfig, setup: AttackSetup, env: gym.Env, store: LabelStore, source: str,
                 snapshots: Path, labeller: Labeller | None = None):
        cfg = self.config = config
        self.snapshots = Path(snapshots)
        self.setup, self.env, self.target = setup, env, setup.target
        self.device = resolve_device(cfg.device)
        self.victim = setup.victim.to(self.device) if isinstance(setup.victim, torch.nn.Module) else setup.victim
        self.rng = seed_everything(cfg.seed)
        obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
        self.learner = PebbleLearner(obs_dim, act_dim, cfg.pebble, store, source=source, rng=self.rng,
                                     labeller=labeller, task=setup.describe.get("task"), target=self.target.name,
                                     device=self.device)
        self.adversary = Adversary(obs_dim, cfg.adversary_hidden).to(self.device)
        self.weighting = WeightingNetwork(obs_dim).to(self.device)
        self.adversary_opt = torch.optim.Adam(self.adversary.parameters(), lr=cfg.adversary_lr)
        self.weighting_opt = torch.optim.Adam(self.weighting.parameters(), lr=cfg.weighting_lr)
        mode = {"no-combined": "intention", "no-intention": "victim"}.get(cfg.ablation, "combined")
        self.behaviour = CombinedBehaviourPolicy(cfg.horizon or episode_length(env), mode)
        self.use_weighting = cfg.ablation not in ("no-weighting", "no-intention")  # no-combined keeps h_ω
        self.counters = {"adversary_updates": 0, "weighting_updates": 0}
        self.best: dict | None = None  # imitate="best": frozen copies of π_θ's actor and critic, its temperature
        self.finished = False
        self.obs: np.ndarray | None = None  # None between episodes
        self.victim_policy = VictimPolicy(self.victim)  # keeps a sequence victim's context over the episode
        self.sequence = is_sequence(self.victim)
        # a sequence victim's context at each stored state, row for row (a run never stores more than its steps):
        capacity = min(self.learner.buffer.capacity, cfg.total_steps)
        self.contexts = np.zeros((capacity, self.victim.context_size), np.float32) if self.sequence else None

    @property
    def step(self) -> int:
        return self.learner.step

    def meta(self) -> dict:
        """What a saved adversary records beside its weights: the configuration, victim, task and target, its shape."""
        return {"rat": to_jsonable(self.config), **self.setup.describe, "target": self.target.name,
                "obs_dim": self.adversary.obs_dim, "adversary_hidden": self.config.adversary_hidden, "method": "rat"}

    def objective(self) -> Imitation:
        """What the adversary imitates now: π_θ as it is (the critic is replaced when PEBBLE resets it), or,
        with ``imitate="best"``, the π_θ that scored best under r̂ at an evaluation."""
        agent, cfg = self.learner.agent, self.config
        if self.best is not None:
            return Imitation(self.victim, self.best["actor"], self.best["critic"], self.best["alpha"], cfg.threat,
                             cfg.victim_std, cfg.kl_form)
        return Imitation(self.victim, agent.actor, agent.critic, agent.alpha, cfg.threat, cfg.victim_std, cfg.kl_form)

    def intention_return(self, actor) -> float:
        """Mean return under the current r̂ of ``actor``'s deterministic episodes (no true reward is used)."""
        def act(obs: np.ndarray) -> np.ndarray:
            return actor(torch.as_tensor(obs, dtype=torch.float32, device=self.device).unsqueeze(0)).squeeze(0).cpu().numpy()

        env = self.setup.make_env(self.config.seed + seeds.SELECTION_ENV)
        return policy_learned_return(act, env, self.learner.ensemble, self.config.imitate_episodes,
                                     seeds.periodic(self.step))

    def keep_best_intention(self) -> dict[str, float]:
        """imitate="best": score π_θ and the kept one under today's r̂, on the same episodes; keep the better."""
        agent = self.learner.agent
        current = self.intention_return(agent.actor)
        kept = self.intention_return(self.best["actor"]) if self.best is not None else -np.inf
        if current >= kept:
            self.best = {"actor": copy.deepcopy(agent.actor).requires_grad_(False),
                         "critic": copy.deepcopy(agent.critic).requires_grad_(False),
                         "alpha": agent.alpha.detach().clone(), "step": self.step}
        return {"intention_learned_return": current, "imitated_step": float(self.best["step"])}

    # --- one environment step (the paper's Algorithm 1) -------------------------------------------

    @torch.no_grad()
    def perturbed(self, obs: np.ndarray) -> np.ndarray:
        """s̃ for the victim; the adversary explores (samples Δ) while collecting."""
        s = torch.as_tensor(obs, dtype=torch.float32, device=self.device).unsqueeze(0)
        return self.config.threat.perturb(s, self.adversary(s, torch.randn_like(s))).squeeze(0).cpu().numpy()

    def advance(self) -> dict[str, float] | None:
        cfg, learner = self.config, self.learner
        if self.obs is None:  # a new episode
            self.obs, _ = self.env.reset(seed=int(self.rng.integers(2**31)))
            self.behaviour.start_episode(self.rng)
            self.victim_policy.reset()
            self.t, self.succeeded, self.metrics = 0, False, {}
            self.success_test = self.target.episode_success()
        obs, victim_turn = self.obs, self.behaviour.victim_acts(self.t)
        context = self.victim.pack_context(self.victim_policy.context).cpu().numpy() if self.sequence else None
        seen = self.perturbed(obs) if victim_turn or self.sequence else None  # what the victim sees, acting or not
        action = self.victim_policy(seen) if victim_turn else learner.act(obs)
        physics = physics_of(self.env) if learner.wants_physics else None  # to film the step for a person
        next_obs, reward, terminated, truncated, info = self.env.step(action)
        r_target = self.target.reward(obs, action, next_obs, info)
        self.metrics.update(learner.observe(obs, action, next_obs, r_target, terminated, truncated, physics))  # labels, r̂, π_θ
        if self.sequence:
            self.contexts[learner.buffer.last_index] = context
            self.victim_policy.observe(reward, *((None, None) if victim_turn else (seen, action)))
        if learner.reward_ready and learner.step % cfg.adversary_every == 0:
            for _ in range(cfg.adversary_updates):
                self.metrics.update(self.adversary_step())  # inner level
            self.metrics["imitation_gap"] = self.objective().gap(self.adversary, *self.last_batch)  # after the phase
            self.metrics["adversary_saturation"] = saturation(self.adversary, self.last_batch[0])
        if self.use_weighting and learner.reward_ready and learner.step % cfg.weighting_every == 0:
            self.metrics.update(self.weighting_step())  # outer level
        self.succeeded |= self.success_test(info)
        self.obs, self.t = next_obs, self.t + 1
        if terminated or truncated:
            self.obs = None
            return {"behaviour_success": float(self.succeeded), "switch_step": self.behaviour.switch, **self.metrics}
        return None

    def sample_states(self) -> tuple[torch.Tensor, object]:
        """A batch of stored states: observations, and a sequence victim's context at each (else None)."""
        buffer = self.learner.buffer
        idx = buffer.sample_indices(self.config.adversary_batch, self.rng)
        obs = buffer.take(idx, self.device)["obs"]
        if not self.sequence:
            return obs, None
        return obs, self.victim.unpack_context(torch.as_tensor(self.contexts[idx], device=self.device))

    def adversary_step(self) -> dict[str, float]:
        obs, context = self.last_batch = self.sample_states()
        self.counters["adversary_updates"] += 1
        return adversary_update(self.adversary, self.adversary_opt, self.weighting if self.use_weighting else None,
                                self.objective(), obs, self.config.ablation, context)

    def weighting_step(self) -> dict[str, float]:
        (obs_inner, context_inner), (obs_outer, context_outer) = self.sample_states(), self.sample_states()
        self.counters["weighting_updates"] += 1
        return weighting_update(self.weighting, self.weighting_opt, self.adversary, self.objective(), obs_inner,
                                obs_outer, self.config.adversary_lr, self.config.hypergradient, context_inner,
                                context_outer)

    # --- evaluation and state ----------------------------------------------------------------------

    def attack(self, refine: bool = False, imitated: IntentionPolicy | None = None,
               gaps: list[float] | None = None) -> Perturbation:
        """The attack as deployed: the adversary's Δ, refined towards π_θ (``imitated``, else the one imitated
        now) if ``refine`` and ``refine_steps`` say so; ``gaps`` then receives the gap left at each observation."""
        cfg = self.config
        if refine and cfg.refine_steps:
            imitated = imitated or IntentionPolicy.of(self.objective())
            return refined_function(self.adversary, imitated.actor, self.victim, cfg.threat, cfg.refine_steps,
                                    cfg.refine_lr, gaps, loss=cfg.refine_loss, critic=imitated.critic, switch_gap=cfg.refine_switch_gap)
        return adversary_function(self.adversary)

    def evaluate_attack(self, episodes: int, seed: int, video=None, refine: bool = False,
                        imitated: IntentionPolicy | None = None, gaps: list[float] | None = None,
                        desc: str | None = None) -> AttackEval:
        """The attack's success now. Evaluations during training use the network's Δ alone (``refine=False``).
        ``desc``: show a progress bar over the episodes with this label (the final evaluations, which a refined
        attack makes long)."""
        cfg = self.config
        make_env = lambda: self.setup.make_env(cfg.seed + seeds.EVAL_ENV)  # noqa: E731 (more of it: lockstep)
        return evaluate_attack(self.victim, self.attack(refine, imitated, gaps), make_env(), self.target, cfg.threat,
                               episodes, seed, video=video, progress=desc is not None and self.setup.progress,
                               desc=desc or "", make_env=make_env)

    def evaluate(self) -> dict[str, float]:
        """The attack now, and a snapshot of the adversary with the π_θ it imitated (for selection by r̂)."""
        res = self.evaluate_attack(self.config.eval_episodes, seeds.periodic(self.step))
        save_checkpoint(self.snapshots / f"adversary-{self.step}", SNAPSHOT,
                        {"adversary": self.adversary.state_dict(), **IntentionPolicy.of(self.objective()).state_dict()},
                        self.meta() | {"step": self.step})
        # π_θ is a candidate once it has learnt from r̂: at the first query round it is still the pre-training
        # explorer, which a young r̂ can score above the learning π_θ for tens of thousands of steps
        learning = self.learner.reward_ready and self.step > self.config.pebble.warm_up
        kept = self.keep_best_intention() if self.config.imitate == "best" and learning else {}
        return {"eval_success_rate": res.result.success_rate, **self.counters, **kept}

    def state_dict(self) -> dict:
        return {"learner": self.learner.state_dict(), "adversary": self.adversary.state_dict(),
                "weighting": self.weighting.state_dict(), "adversary_opt": self.adversary_opt.state_dict(),
                "weighting_opt": self.weighting_opt.state_dict(), "rng": rng_state(self.rng),
                "counters": dict(self.counters)} | ({} if self.contexts is None else {
                    "contexts": self.contexts[:len(self.learner.buffer)]}) | ({} if self.best is None else {"best": {
                    "actor": self.best["actor"].state_dict(), "critic": self.best["critic"].state_dict(),
                    "alpha": self.best["alpha"], "step": torch.tensor(self.best["step"])}})

    def load_state_dict(self, state: dict, meta: dict) -> None:
        self.learner.load_state_dict(state["learner"])
        self.learner.restore_meta(meta)
        self.adversary.load_state_dict(state["adversary"])
        self.weighting.load_state_dict(state["weighting"])
        self.adversary_opt.load_state_dict(state["adversary_opt"])
        self.weighting_opt.load_state_dict(state["weighting_opt"])
        restore_rng_state(self.rng, state["rng"])
        self.counters.update({k: int(state["counters"][k]) for k in self.counters})
        if self.contexts is not None:
            self.contexts[:len(state["contexts"])] = state["contexts"]
        if "best" in state:
            agent, b = self.learner.agent, state["best"]
            self.best = {"actor": copy.deepcopy(agent.actor).requires_grad_(False),
                         "critic": copy.deepcopy(agent.critic).requires_grad_(False),
                         "alpha": torch.as_tensor(b["alpha"]).to(self.device), "step": int(b["step"])}
            self.best["actor"].load_state_dict(b["actor"])
            self.best["critic"].load_state_dict(b["critic"])

    def checkpoint_meta(self) -> dict:
        return self.learner.checkpoint_meta()


def as_run(config: RATConfig, env: gym.Env) -> RATConfig:
    """``config`` as a run in ``env`` records it: the horizon resolved to the env's time limit where unset."""
    return replace(config, horizon=config.horizon or episode_length(env))


def training_title(target: str, describe: dict) -> str:
    """What a run's plot is of, so that two runs' plots are told apart: the target, the victim, and the task the
    behaviour is sought in where that is not the victim's own (an opposite row)."""
    title = f"RAT {target}"
    if describe.get("victim"):
        title += f" against {describe['victim']}"
    if describe.get("task") and describe.get("task") != describe.get("victim_task"):
        title += f" in {describe['task']}"
    return title


def train_rat(config: RATConfig, setup: AttackSetup, out: str | Path, tensorboard: bool = False) -> AttackReport:
    """Train a RAT adversary against ``setup.victim`` for ``setup.target`` (resumable from ``out``).

    Returns the report (also in ``out/report.json``); the adversary is ``out/adversary.*``.
    """
    cfg, target = config, setup.target
    cfg.pebble.check_budget("RAT")  # here, not in RATConfig: an oracle run's zero budget is fine, and only the setup says oracle
    env = setup.make_env(cfg.seed)  # checked before the run directory exists, so a mistake leaves nothing behind
    cfg = as_run(cfg, env)  # recorded as used
    task = setup.describe.get("task")
    check_compatible(setup.victim, env, f"task '{task}'" if task else "the environment")
    run = Run(out, {"rat": cfg, **setup.describe}, tensorboard)  # the dataclass: a later setting at its default resumes
    store = LabelStore(run.dir / "labels.sqlite")
    trainer = RATTrainer(cfg, setup, env, store, run.dir.name, run.dir / "snapshots", setup.labeller)
    loop = TrainingLoop(run, trainer, cfg.total_steps, eval_every=cfg.eval_every, checkpoint_every=cfg.checkpoint_every,
                        checkpoint_at_boundary=True, desc=f"RAT {target.name}", progress=setup.progress)
    loop.resume()
    train_seconds = loop.run()

    # --- results -------------------------------------------------------------------------------------
    adversary = trainer.adversary
    meta = trainer.meta()
    # π_θ as the adversary imitated it, and its critic, saved beside it: refinement (refine_steps) aims at them
    imitated = IntentionPolicy.of(trainer.objective())
    details: dict = {"ablation": cfg.ablation, "queries_asked": trainer.learner.asked, **trainer.counters}
    if cfg.select == "reward":  # the attacker's own yardstick: r̂, never the true target reward
        save_checkpoint(run.dir / "adversary-last", "adversary",
                        {"adversary": adversary.state_dict(), **imitated.state_dict()}, meta)
        last = trainer.evaluate_attack(cfg.final_eval_episodes, seeds.FINAL, refine=True, desc="the last adversary")
        selected = select_by_learned_reward(trainer.snapshots, adversary, trainer.victim, trainer.learner.ensemble,
                                            setup.make_env(cfg.seed + seeds.SELECTION_ENV), cfg)
        snapshot = selected.pop("imitated")  # a snapshot's: the π_θ it imitated, not the last one
        if snapshot is not None:
            imitated = snapshot.to(trainer.device)
        details.update(selected, last_attack_success_rate=last.result.success_rate)
    if cfg.refine_steps:  # the network's Δ alone, beside the refined attack
        details["network_attack_success_rate"] = trainer.evaluate_attack(
            cfg.final_eval_episodes, seeds.FINAL, desc="the network's Δ alone").result.success_rate
    gaps: list[float] = []  # what refinement left of ‖μ_ν(s̃) − tanh μ_θ(s)‖ along the attacked episodes
    final = trainer.evaluate_attack(cfg.final_eval_episodes, seeds.FINAL, refine=True, imitated=imitated, gaps=gaps,
                                    desc="the attack")
    if gaps:  # large where π_θ asks for actions the ball cannot make the victim take (docs/notes/strength-log.md)
        details["refined_gap"] = float(np.mean(gaps))
    save_checkpoint(run.dir / "adversary", "adversary", {"adversary": adversary.state_dict(), **imitated.state_dict()},
                    meta | {"selected_step": details.get("selected_step", trainer.step)})
    title = training_title(target.name, setup.describe)
    if cfg.refine_steps:  # the evaluations during training measure the network's Δ; the attack refines it
        plot_training(run.logger.path, run.dir / "training.png", f"{title}\nattack success",
                      curve="the network's Δ alone, during training",
                      final=(trainer.step, final.result.success_rate,
                             f"the attack, Δ refined ({cfg.final_eval_episodes} episodes)"))
    else:
        plot_training(run.logger.path, run.dir / "training.png", f"{title}\nattack success during training")
    report = conclude(run, "rat", "oracle" if cfg.pebble.oracle else "labels", setup, cfg.seed, final,
                      cfg.final_eval_episodes, steps=trainer.step, labels=store.count(trainer.learner.source),
                      minutes=train_seconds / 60, train_minutes=loop.total_seconds / 60, details=details,
                      victim=trainer.victim)
    store.close()
    return report


@register_attack("rat", config=RATConfig, rewards=("labels", "oracle"))
class RAT:
    """RAT: the adversary imitates an intention policy learned from preference labels (the paper's method)."""

    def train(self, setup: AttackSetup, config: RATConfig, out: Path) -> AttackReport:
        return train_rat(self.configure(setup, config), setup, out, setup.tensorboard)

    @staticmethod
    def configure(setup: AttackSetup, config: RATConfig) -> RATConfig:
        """``config`` as the setup decides it: threat, reward source and seed. An oracle run learns no r̂
        to score snapshots or π_θ with, so it keeps the last adversary and imitates π_θ as it is."""
        oracle = setup.reward == "oracle"
        scored = {"select": "last", "imitate": "current"} if oracle else {}
        return replace(config, seed=setup.seed, epsilon=setup.threat.epsilon, norm=setup.threat.norm,
                       pebble=replace(config.pebble, oracle=oracle), **scored)

    def load(self, run: Path, meta: dict, victim: Victim) -> Perturbation:
        return load_rat_attack(run, victim)
