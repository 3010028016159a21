"""A RAT run's adversaries, as saved: the π_θ each imitated, choosing among them by the learned reward, and
loading one back as an attack (refined or not)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np
import torch

from rat import seeds
from rat.agents.networks import TanhGaussianActor, TwinCritic
from rat.attacks.base import SNAPSHOT, saved_attack_meta
from rat.attacks.losses import Adversary, Imitation
from rat.attacks.refine import CRITIC_LOSSES, refined_function
from rat.attacks.threat import AttackedObservation, Perturbation, ThreatModel
from rat.checkpoint import load_checkpoint
from rat.errors import RatError
from rat.victims.base import Victim, VictimPolicy

if TYPE_CHECKING:
    from rat.attacks.rat import RATConfig


def adversary_function(adversary: Adversary) -> Perturbation:
    """The trained adversary's deterministic Δ for one observation (numpy)."""
    device = next(adversary.parameters()).device

    @torch.no_grad()
    def delta(obs: np.ndarray) -> np.ndarray:
        s = torch.as_tensor(obs, dtype=torch.float32, device=device).unsqueeze(0)
        return adversary(s).squeeze(0).double().cpu().numpy()

    return delta


@dataclass(frozen=True)
class IntentionPolicy:
    """The π_θ an adversary imitated, its actor and its critic Q_φ, as saved beside the adversary: what
    refinement aims at (``critic`` is None in files saved before it was kept)."""

    actor: TanhGaussianActor
    critic: TwinCritic | None = None

    @classmethod
    def of(cls, objective: Imitation) -> IntentionPolicy:
        return cls(objective.intention, objective.critic)

    @classmethod
    def from_state(cls, state: dict) -> IntentionPolicy | None:
        """The π_θ in a saved adversary's state; None where it holds none (an older version's)."""
        if "intention" not in state:
            return None
        actor = TanhGaussianActor.from_state_dict(state["intention"]).requires_grad_(False)
        critic = state.get("critic")
        return cls(actor, None if critic is None else
                   TwinCritic.from_state_dict(critic, actor.obs_dim).requires_grad_(False))

    def state_dict(self) -> dict:
        critic = {} if self.critic is None else {"critic": self.critic.state_dict()}
        return {"intention": self.actor.state_dict(), **critic}

    def to(self, device) -> IntentionPolicy:
        return IntentionPolicy(self.actor.to(device), None if self.critic is None else self.critic.to(device))


@torch.no_grad()
def policy_learned_return(policy: Callable[[np.ndarray], np.ndarray], env: gym.Env, ensemble, episodes: int,
                          seed: int) -> float:
    """Mean return under r̂ of ``policy``'s episodes (``obs -> action``; episode ``i`` reset with ``seed + i``).

    r̂ scores the true state (``info["true_obs"]`` under an attack); a policy with ``reset()`` and
    ``observe(reward)`` (a :class:`~rat.victims.base.VictimPolicy`) is told where episodes start and what happened.
    """
    returns = []
    for episode in range(episodes):
        obs, info = env.reset(seed=seed + episode)
        if hasattr(policy, "reset"):
            policy.reset()
        total, done = 0.0, False
        while not done:
            action = policy(obs)
            total += float(ensemble.r_hat(np.asarray(info.get("true_obs", obs), np.float32), action))
            obs, reward, terminated, truncated, info = env.step(action)
            if hasattr(policy, "observe"):
                policy.observe(reward)
            done = terminated or truncated
        returns.append(total)
    return float(np.mean(returns))


def learned_return(victim: Victim, adversary: Adversary, env: gym.Env, ensemble, threat: ThreatModel, episodes: int,
                   seed: int) -> float:
    """Mean return under r̂ of the attacked victim's episodes: how well the attack does, by the attacker's model."""
    attacked = AttackedObservation(env, adversary_function(adversary), threat)
    return policy_learned_return(VictimPolicy(victim), attacked, ensemble, episodes, seed)


def select_by_learned_reward(snapshots: Path, adversary: Adversary, victim: Victim, ensemble, env: gym.Env,
                             cfg: RATConfig) -> dict:
    """Load into ``adversary`` the snapshot (or the last one) whose attack the final r̂ scores highest.

    Every candidate is scored on the same episodes; ties go to the later one. Uses no true reward.
    Returns the selected step, every candidate's score and, as ``imitated``, the π_θ a selected snapshot
    imitated, with its critic (None for the last adversary, or a snapshot saved without π_θ).
    """
    candidates = {"last": ({k: v.clone() for k, v in adversary.state_dict().items()}, None)}
    for path in sorted(snapshots.glob("adversary-*.json"), key=lambda p: int(p.stem.split("-")[1])):
        state = load_checkpoint(path, SNAPSHOT)[0]
        candidates[path.stem.split("-")[1]] = (state["adversary"], IntentionPolicy.from_state(state))
    scores = {}
    for name, (state, _) in candidates.items():
        adversary.load_state_dict(state)
        scores[name] = learned_return(victim, adversary, env, ensemble, cfg.threat, cfg.eval_episodes, seeds.SELECTION)
    order = [n for n in candidates if n != "last"] + ["last"]  # later wins ties
    best = max(reversed(order), key=lambda n: scores[n])
    adversary.load_state_dict(candidates[best][0])
    return {"selected_step": cfg.total_steps if best == "last" else int(best),
            "learned_returns": {n: round(v, 3) for n, v in scores.items()}, "imitated": candidates[best][1]}


def load_adversary(path: str | Path) -> tuple[Adversary, dict]:
    """An adversary saved by :func:`train_rat` (``<run>/adversary``), with its metadata."""
    adversary, _, meta = load_saved(path)
    return adversary, meta


def load_saved(path: str | Path) -> tuple[Adversary, IntentionPolicy | None, dict]:
    """The adversary of ``<run>/adversary`` (or of another saved adversary file, a snapshot
    ``<run>/snapshots/adversary-<step>`` too), the π_θ it imitated with its critic (None if the run predates
    saving π_θ) and the metadata."""
    path = Path(path)
    if path.is_dir():
        path = path / "adversary"
    meta = saved_attack_meta(path)
    state, _ = load_checkpoint(path, SNAPSHOT if "snapshot_step" in meta else "adversary")
    adversary = Adversary(int(meta["obs_dim"]), int(meta["adversary_hidden"]))
    adversary.load_state_dict(state["adversary"])
    adversary.eval().requires_grad_(False)
    return adversary, IntentionPolicy.from_state(state), meta


def load_rat_attack(run: str | Path, victim: Victim, refine_steps: int | None = None,
                    gaps: list[float] | None = None, refine_loss: str | None = None,
                    switch_gap: float | None = None) -> Perturbation:
    """A RAT run's attack, as ``obs -> Δ``: the adversary's Δ, refined towards π_θ by ``refine_steps``
    Adam steps per observation minimising ``refine_loss``, with ``switch_gap`` as ``l2-or-q``'s threshold
    (None: as the run was configured; 0 steps: the network's Δ alone). ``gaps``, if given, receives the gap
    refinement leaves at each observation."""
    adversary, imitated, meta = load_saved(run)
    cfg = meta.get("rat", {})
    steps = cfg.get("refine_steps", 0) if refine_steps is None else refine_steps
    if steps < 0:
        raise RatError(f"refine-steps must be ≥ 0, got {steps}")
    if not steps:
        if refine_loss is not None or switch_gap is not None:  # asked for, but nothing would be refined: say so
            what = f"refine-loss '{refine_loss}'" if refine_loss is not None else f"refine-switch-gap {switch_gap}"
            raise RatError(f"{what} chooses how Δ is refined, and '{run}' refines 0 steps; give --refine-steps N "
                           "(N > 0) with it")
        return adversary_function(adversary)
    if imitated is None:
        raise RatError(f"the RAT run '{run}' did not save the intention policy beside its adversary (older version); "
                       "run its `rat attack train` command again to rewrite it, or evaluate without refinement")
    from rat.attacks.rat import RATConfig  # the run's own settings, or RAT's defaults where it predates one

    loss = refine_loss or cfg.get("refine_loss", RATConfig.refine_loss)
    if switch_gap is not None and loss != "l2-or-q":  # asked for, but no pass would read it
        raise RatError(f"refine-switch-gap is the threshold of refine-loss 'l2-or-q', and '{run}' is refined by "
                       f"'{loss}'; give --refine-loss l2-or-q with it, or drop it")
    if loss in CRITIC_LOSSES and imitated.critic is None:
        raise RatError(f"refine-loss '{loss}' climbs π_θ's critic, and '{run}' saved none beside its adversary (an "
                       "unreleased version's run); refine with 'l2', or run its `rat attack train` command again")
    return refined_function(adversary, imitated.actor, victim, ThreatModel(cfg["epsilon"], cfg["norm"]), steps,
                            cfg.get("refine_lr", RATConfig.refine_lr), gaps, loss=loss, critic=imitated.critic,
                            switch_gap=cfg.get("refine_switch_gap", RATConfig.refine_switch_gap)
                            if switch_gap is None else switch_gap)
