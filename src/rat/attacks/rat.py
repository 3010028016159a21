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
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import gymnasium as gym
import numpy as np
import torch
from tqdm.auto import tqdm

from rat.attacks.losses import Adversary, WeightingNetwork, hypergradient, inner_loss, kl_per_state, outer_loss
from rat.attacks.threat import AttackedObservation, check_budget, perturb, perturbation_norm
from rat.checkpoint import load_checkpoint, save_checkpoint
from rat.envs.targets import TargetBehaviour
from rat.errors import RatError
from rat.eval import EvalResult, evaluate
from rat.agents.sac import SAC
from rat.plots import plot_training
from rat.preferences.pebble import PebbleConfig, PebbleLearner
from rat.preferences.store import LabelStore
from rat.runs import Run, restore_rng_state, rng_state, seed_everything, to_jsonable
from rat.victims.base import Victim, check_compatible, numpy_policy

ABLATIONS = ("none", "no-weighting", "no-combined", "no-intention")


@dataclass(frozen=True)
class RATConfig:
    """A RAT attack (defaults: the paper's, with ``algorithm.md``'s released schedule)."""

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
    horizon: int = 500  #: episode length H of the combined behaviour policy's switch
    eval_every: int = 10_000  #: steps between attack evaluations
    eval_episodes: int = 10  #: episodes per evaluation during training
    final_eval_episodes: int = 30  #: episodes of the final evaluation (the paper's 30)
    select: str = "last"  #: "last" adversary (the paper's), or the snapshot whose attack scores best under r̂ ("reward")
    checkpoint_every: int = 10_000  #: a checkpoint at the first episode end after this many steps

    def __post_init__(self):
        check_budget(self.epsilon, self.norm)
        if self.ablation not in ABLATIONS:
            raise RatError(f"unknown ablation '{self.ablation}'; use one of: {', '.join(ABLATIONS)}")
        if self.select not in ("last", "reward"):
            raise RatError(f"select must be last or reward, got '{self.select}'")
        if self.select == "reward" and self.pebble.oracle:
            raise RatError("select=reward scores snapshots with r̂, which an oracle run does not learn; use select=last")
        if self.kl_form not in ("exact", "released") or self.hypergradient not in ("exact", "batch-mean"):
            raise RatError("kl-form must be exact or released, hypergradient exact or batch-mean")
        for name in ("total_steps", "adversary_every", "adversary_updates", "adversary_batch", "weighting_every",
                     "horizon", "eval_every", "eval_episodes", "final_eval_episodes", "checkpoint_every"):
            if getattr(self, name) <= 0:
                raise RatError(f"{name.replace('_', '-')} must be positive, got {getattr(self, name)}")


class CombinedBehaviourPolicy:
    """Who acts at each episode step: the perturbed victim before a switch step h, π_θ from h on.

    h ~ U{0, …, H−1} is drawn at every episode start (``"combined"``); ``"intention"`` and
    ``"victim"`` fix h = 0 and h = H.
    """

    def __init__(self, horizon: int, mode: str = "combined"):
        self.horizon, self.mode, self.switch = horizon, mode, 0

    def start_episode(self, rng: np.random.Generator) -> None:
        self.switch = {"combined": lambda: int(rng.integers(0, self.horizon)), "intention": lambda: 0,
                       "victim": lambda: self.horizon}[self.mode]()

    def victim_acts(self, episode_step: int) -> bool:
        return episode_step < self.switch


@dataclass
class AttackEval:
    """An attack's evaluation: the target success of the attacked victim, and perturbation sizes."""

    result: EvalResult
    norm: str
    epsilon: float
    max_perturbation: float
    mean_perturbation: float
    steps: int

    @property
    def within_budget(self) -> bool:
        return self.max_perturbation <= self.epsilon * (1 + 1e-6) + 1e-12

    def summary(self) -> str:
        return (f"{self.result.summary()}; perturbation {self.norm} mean {self.mean_perturbation:.4f}, "
                f"max {self.max_perturbation:.4f} <= epsilon {self.epsilon:g} ({self.norm}, raw observation units)")


def evaluate_attack(victim: Victim, adversary: Callable[[np.ndarray], np.ndarray], env: gym.Env,
                    target: TargetBehaviour, epsilon: float, norm: str, episodes: int, seed: int,
                    video: str | Path | None = None, progress: bool = False, video_episodes=2) -> AttackEval:
    """Run the victim on attacked observations; success is the *target*'s test, at any step."""
    attacked = AttackedObservation(env, adversary, epsilon, norm)
    result = evaluate(numpy_policy(victim), attacked, episodes, seed, target=target, video=video, progress=progress,
                      video_episodes=video_episodes)
    norms = np.asarray(attacked.norms)
    return AttackEval(result, norm, epsilon, float(norms.max()), float(norms.mean()), len(norms))


def adversary_function(adversary: Adversary) -> Callable[[np.ndarray], np.ndarray]:
    """The trained adversary's deterministic Δ for one observation (numpy)."""

    @torch.no_grad()
    def delta(obs: np.ndarray) -> np.ndarray:
        return adversary(torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)).squeeze(0).double().numpy()

    return delta


def adversary_update(adversary: Adversary, optimizer: torch.optim.Optimizer, weighting: WeightingNetwork | None,
                     victim: Victim, intention: SAC, obs: torch.Tensor, cfg: RATConfig) -> dict[str, float]:
    """One inner-level step: only the adversary's parameters receive a gradient and change.

    Minimises the weighted KL to the intention policy (weights 1 without a weighting network),
    or, for the ``no-intention`` ablation, the outer loss itself.
    """
    noise = torch.randn_like(obs)
    if cfg.ablation == "no-intention":
        loss = outer_loss(adversary, None, victim, intention.critic, intention.alpha, obs, noise, cfg.epsilon,
                          cfg.norm, cfg.victim_std)
    else:
        with torch.no_grad():
            weights = weighting(obs) if weighting is not None else torch.ones(len(obs))
        kl = kl_per_state(adversary, None, victim, intention.actor, obs, noise, cfg.epsilon, cfg.norm, cfg.victim_std,
                          cfg.kl_form)
        loss = inner_loss(weights, kl)
    optimizer.zero_grad(set_to_none=True)
    loss.backward(inputs=list(adversary.parameters()))  # nothing else may accumulate a gradient
    optimizer.step()
    return {"adversary_loss": loss.item()}


def weighting_update(weighting: WeightingNetwork, optimizer: torch.optim.Optimizer, adversary: Adversary,
                     victim: Victim, intention: SAC, obs_inner: torch.Tensor, obs_outer: torch.Tensor,
                     cfg: RATConfig) -> dict[str, float]:
    """One outer-level step: the hypergradient moves the weighting network, and nothing else."""
    grads = hypergradient(adversary, weighting, victim, intention.actor, intention.critic, intention.alpha, obs_inner,
                          torch.randn_like(obs_inner), obs_outer, torch.randn_like(obs_outer), cfg.epsilon, cfg.norm,
                          cfg.adversary_lr, cfg.victim_std, cfg.kl_form, cfg.hypergradient)
    optimizer.zero_grad(set_to_none=True)
    for p, g in zip(weighting.parameters(), grads):
        p.grad = None if g is None else g.detach()
    optimizer.step()
    with torch.no_grad():
        w = weighting(obs_inner)
    return {"weight_mean": w.mean().item(), "weight_std": w.std().item()}


def train_rat(config: RATConfig, victim: Victim, target: TargetBehaviour, make_env: Callable[[int], gym.Env],
              out: str | Path, describe: dict | None = None, progress: bool = True, tensorboard: bool = False) -> dict:
    """Train a RAT adversary against a frozen ``victim`` for ``target`` (resumable from ``out``).

    Args:
        make_env: ``seed -> environment`` of the target behaviour (the true state is never perturbed).
        describe: JSON-able facts saved with the run and the adversary (victim spec, task, ...).

    Returns the report (also in ``out/report.json``); the adversary is ``out/adversary.*``.
    """
    cfg = config
    env = make_env(cfg.seed)  # checked before the run directory exists, so a mistake leaves nothing behind
    check_compatible(victim, env, f"task '{describe['task']}'" if describe and "task" in describe else "the environment")
    run = Run(out, {"rat": to_jsonable(cfg), **(describe or {})}, tensorboard)
    rng = seed_everything(cfg.seed)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    store = LabelStore(run.dir / "labels.sqlite")
    learner = PebbleLearner(obs_dim, act_dim, cfg.pebble, store, source=run.dir.name, rng=rng,
                            task=(describe or {}).get("task"), target=target.name)
    adversary = Adversary(obs_dim, cfg.adversary_hidden)
    weighting = WeightingNetwork(obs_dim)
    adv_opt = torch.optim.Adam(adversary.parameters(), lr=cfg.adversary_lr)
    w_opt = torch.optim.Adam(weighting.parameters(), lr=cfg.weighting_lr)
    mode = {"no-combined": "intention", "no-intention": "victim"}.get(cfg.ablation, "combined")
    behaviour = CombinedBehaviourPolicy(cfg.horizon, mode)
    use_weighting = cfg.ablation == "none"
    counters = {"adversary_updates": 0, "weighting_updates": 0, "next_checkpoint": cfg.checkpoint_every}

    def save(path: Path) -> None:
        save_checkpoint(path, "rat-run", {
            "learner": learner.state_dict(), "adversary": adversary.state_dict(), "weighting": weighting.state_dict(),
            "adversary_opt": adv_opt.state_dict(), "weighting_opt": w_opt.state_dict(), "rng": rng_state(rng),
            "counters": counters}, {"step": learner.step})

    if run.has_checkpoint():
        state, _ = load_checkpoint(run.checkpoint_path, "rat-run")
        learner.load_state_dict(state["learner"])
        adversary.load_state_dict(state["adversary"])
        weighting.load_state_dict(state["weighting"])
        adv_opt.load_state_dict(state["adversary_opt"])
        w_opt.load_state_dict(state["weighting_opt"])
        restore_rng_state(rng, state["rng"])
        counters.update({k: int(v) for k, v in state["counters"].items()})
        run.logger.truncate_after(learner.step)

    def victim_action(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            s = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
            delta = adversary(s, torch.randn_like(s))  # the adversary explores while collecting
            return victim.act(perturb(s, delta, cfg.epsilon, cfg.norm)).squeeze(0).numpy()

    def adversary_step() -> dict[str, float]:
        obs = learner.buffer.sample(cfg.adversary_batch, rng)["obs"]
        counters["adversary_updates"] += 1
        return adversary_update(adversary, adv_opt, weighting if use_weighting else None, victim, learner.agent, obs, cfg)

    def weighting_step() -> dict[str, float]:
        obs_inner = learner.buffer.sample(cfg.adversary_batch, rng)["obs"]
        obs_outer = learner.buffer.sample(cfg.adversary_batch, rng)["obs"]
        counters["weighting_updates"] += 1
        return weighting_update(weighting, w_opt, adversary, victim, learner.agent, obs_inner, obs_outer, cfg)

    def evaluate_now(episodes: int, seed: int, video=None) -> AttackEval:
        return evaluate_attack(victim, adversary_function(adversary), make_env(cfg.seed + 7), target, cfg.epsilon,
                               cfg.norm, episodes, seed, video=video)

    # --- the loop (the paper's Algorithm 1) ------------------------------------------------------------
    started = time.perf_counter()
    bar = tqdm(total=cfg.total_steps, initial=learner.step, desc=f"RAT {target.name}", disable=not progress)
    obs, _ = env.reset(seed=int(rng.integers(2**31)))
    behaviour.start_episode(rng)
    t, ep_success, metrics = 0, False, {}
    while learner.step < cfg.total_steps:
        action = victim_action(obs) if behaviour.victim_acts(t) else learner.act(obs)
        next_obs, _, terminated, truncated, info = env.step(action)
        r_target = target.reward(obs, action, next_obs, info)
        metrics.update(learner.observe(obs, action, next_obs, r_target, terminated, truncated))  # labels, r̂, π_θ
        if learner.reward_ready and learner.step % cfg.adversary_every == 0:
            for _ in range(cfg.adversary_updates):
                metrics.update(adversary_step())  # inner level
        if use_weighting and learner.reward_ready and learner.step % cfg.weighting_every == 0:
            metrics.update(weighting_step())  # outer level
        ep_success |= target.success(info)
        obs, t = next_obs, t + 1
        bar.update(1)
        if learner.step % cfg.eval_every == 0:
            res = evaluate_now(cfg.eval_episodes, seed=10**7 + learner.step)
            save_checkpoint(run.dir / "snapshots" / f"adversary-{learner.step}", "adversary-snapshot",
                            {"adversary": adversary.state_dict()}, {"step": learner.step})
            run.logger.log(learner.step, {"eval_success_rate": res.result.success_rate, **counters})
            bar.set_postfix(attack_success=f"{res.result.success_rate:.0%}", labels=learner.asked)
        if terminated or truncated:
            run.logger.log(learner.step, {"behaviour_success": float(ep_success), "switch_step": behaviour.switch,
                                          **metrics})
            if learner.step >= counters["next_checkpoint"]:
                counters["next_checkpoint"] += cfg.checkpoint_every
                save(run.checkpoint_path)
            obs, _ = env.reset(seed=int(rng.integers(2**31)))
            behaviour.start_episode(rng)
            t, ep_success, metrics = 0, False, {}
    bar.close()
    train_seconds = time.perf_counter() - started

    # --- results -------------------------------------------------------------------------------------
    meta = {"rat": to_jsonable(cfg), **(describe or {}), "target": target.name, "obs_dim": obs_dim,
            "adversary_hidden": cfg.adversary_hidden}
    selection: dict = {}
    if cfg.select == "reward":  # the attacker's own yardstick: r̂, never the true target reward
        save_checkpoint(run.dir / "adversary-last", "adversary", {"adversary": adversary.state_dict()}, meta)
        last = evaluate_now(cfg.final_eval_episodes, seed=2 * 10**7)
        selection = select_by_learned_reward(run.dir / "snapshots", adversary, victim, learner.ensemble,
                                             make_env(cfg.seed + 11), cfg)
        selection["last_attack_success_rate"] = last.result.success_rate
    final = evaluate_now(cfg.final_eval_episodes, seed=2 * 10**7)
    if not final.within_budget:  # a guard on the threat model itself, never expected to fire
        raise RuntimeError(f"perturbation {final.max_perturbation} exceeded epsilon {cfg.epsilon}")
    save_checkpoint(run.dir / "adversary", "adversary", {"adversary": adversary.state_dict()},
                    meta | {"selected_step": selection.get("selected_step", learner.step)})
    plot_training(run.logger.path, run.dir / "training.png", f"RAT {target.name}: attack success during training")
    report = {
        **(describe or {}), "target": target.name, "epsilon": cfg.epsilon, "norm": cfg.norm,
        "ablation": cfg.ablation, "steps": learner.step, "labels": store.count(learner.source),
        "queries_asked": learner.asked, "attack_success_rate": final.result.success_rate,
        "attack_success_ci": list(final.result.success_ci), "episodes": final.result.episodes,
        "max_perturbation": final.max_perturbation, "mean_perturbation": final.mean_perturbation,
        "adversary_updates": counters["adversary_updates"], "weighting_updates": counters["weighting_updates"],
        "train_minutes_this_session": round(train_seconds / 60, 2), **selection,
    }
    (run.dir / "report.json").write_text(json.dumps(report, indent=1))
    store.close()
    return report


@torch.no_grad()
def learned_return(victim: Victim, adversary: Adversary, env: gym.Env, ensemble, cfg: RATConfig, episodes: int,
                   seed: int) -> float:
    """Mean return under r̂ of the attacked victim's episodes: how well the attack does, by the attacker's model."""
    delta = adversary_function(adversary)
    returns = []
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        total, done = 0.0, False
        while not done:
            s = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
            d = torch.as_tensor(delta(obs), dtype=torch.float32).unsqueeze(0)
            action = victim.act(perturb(s, d, cfg.epsilon, cfg.norm)).squeeze(0).numpy()
            total += float(ensemble.r_hat(obs.astype(np.float32), action))
            obs, _, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
        returns.append(total)
    return float(np.mean(returns))


def select_by_learned_reward(snapshots: Path, adversary: Adversary, victim: Victim, ensemble, env: gym.Env,
                             cfg: RATConfig) -> dict:
    """Load into ``adversary`` the snapshot (or the last one) whose attack the final r̂ scores highest.

    Every candidate is scored on the same episodes; ties go to the later one. Uses no true reward.
    """
    candidates = {"last": {k: v.clone() for k, v in adversary.state_dict().items()}}
    for path in sorted(snapshots.glob("adversary-*.json"), key=lambda p: int(p.stem.split("-")[1])):
        candidates[path.stem.split("-")[1]] = load_checkpoint(path, "adversary-snapshot")[0]["adversary"]
    scores = {}
    for name, state in candidates.items():
        adversary.load_state_dict(state)
        scores[name] = learned_return(victim, adversary, env, ensemble, cfg, cfg.eval_episodes, seed=3 * 10**7)
    order = [n for n in candidates if n != "last"] + ["last"]  # later wins ties
    best = max(reversed(order), key=lambda n: scores[n])
    adversary.load_state_dict(candidates[best])
    return {"selected_step": cfg.total_steps if best == "last" else int(best),
            "learned_returns": {n: round(v, 3) for n, v in scores.items()}}


def load_adversary(path: str | Path) -> tuple[Adversary, dict]:
    """An adversary saved by :func:`train_rat` (``<run>/adversary``), with its metadata."""
    path = Path(path)
    if path.is_dir():
        path = path / "adversary"
    state, meta = load_checkpoint(path, "adversary")
    adversary = Adversary(int(meta["obs_dim"]), int(meta["adversary_hidden"]))
    adversary.load_state_dict(state["adversary"])
    adversary.eval().requires_grad_(False)
    return adversary, meta
