"""RAT's attack as deployed, refined: at every observation, Adam steps on Δ towards π_θ's action there (a
departure; ``docs/design.md`` §10). :class:`RefinedAttack` is an ``obs -> Δ`` like any attack, and refines the
observations of several episodes at once for evaluation in lockstep."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from rat.agents.networks import TanhGaussianActor, TwinCritic
from rat.attacks.losses import Adversary, intention_gaussian
from rat.attacks.threat import ThreatModel
from rat.errors import RatError
from rat.victims.base import Victim, is_sequence, prepared

REFINE_SWITCH_GAP = 1.0  #: l2-or-q's default threshold on the gap l2 leaves (RATConfig.refine_switch_gap)

REFINE_LOSSES = ("l2", "q", "l2-or-q")  #: what refinement at attack time minimises (RATConfig.refine_loss)
CRITIC_LOSSES = ("q", "l2-or-q")  #: the refinement losses that need π_θ's critic


def check_refine_loss(loss: str) -> None:
    """One line naming the choices, for a refinement loss that is not one of them."""
    if loss not in REFINE_LOSSES:
        raise RatError(f"refine-loss must be one of {', '.join(REFINE_LOSSES)}, got '{loss}'")


class RefinedAttack:
    """The adversary's Δ, refined at every observation towards π_θ's action there (a departure; ``docs/design.md`` §10).

    From the network's Δ, ``steps`` Adam steps on Δ itself (through tanh, so Δ stays in (−1, 1)^d and
    the perturbation in the ball) minimise this one state's imitation loss: ``loss="l2"``, the squared
    gap ‖μ_ν(s + ε·P(Δ)) − tanh μ_θ(s)‖², every action dimension alike; ``loss="q"``, the paper's outer objective at this state,
    −min Q_φ(s, μ_ν(s̃)) with π_θ's critic (``critic``): where π_θ's action lies beyond what the ball can make
    the victim take, the action within reach that π_θ's critic values most, rather than the one nearest π_θ's
    (a departure; ``docs/design.md`` §10); ``loss="l2-or-q"``, ``l2``, then ``q`` at the observations where ``l2``
    leaves a gap above ``switch_gap`` (π_θ's action out of reach). The Δ with the smallest loss seen is used. The steps start
    from the network's Δ or from the Δ chosen at the episode's previous observation, whichever leaves the
    smaller loss here (consecutive states are close). It needs what training already does — the victim's
    gradient and π_θ — and costs ``steps`` forward and backward passes of the victim per observation.
    A sequence victim acts on its context too: the attack keeps each episode's own, from what it is told of
    every step (:meth:`observe`: the observation as the victim saw it, the action, the reward), exactly as
    the victim's keeper does, and refines Δ for the current observation with the context fixed — the past
    perturbed states stay as they were seen (``docs/design.md`` §9, §10) — so the past runs through the victim
    once per observation, not once per step (its ``prepare``, where it has one). ``gaps``, if given, receives the
    gap ‖μ_ν(s̃) − tanh μ_θ(s)‖ left at each observation (whichever loss chose Δ).

    Called with one observation it is a :data:`~rat.attacks.threat.Perturbation`; :meth:`batch` refines the
    observations of several episodes at once (``slots`` name their episodes), each exactly as alone — Adam
    acts on every element on its own and each row's loss has only its own Δ — but in one pass of the
    networks per step, which is what makes evaluating it in lockstep (``evaluate_attack(make_env=...)``) fast.
    """

    def __init__(self, adversary: Adversary, intention: TanhGaussianActor, victim: Victim, threat: ThreatModel,
                 steps: int, lr: float = 0.1, gaps: list[float] | None = None, *, loss: str = "l2",
                 critic: TwinCritic | None = None, switch_gap: float = REFINE_SWITCH_GAP):
        check_refine_loss(loss)
        if switch_gap < 0:
            raise RatError(f"refine-switch-gap must be ≥ 0, got {switch_gap}")
        if loss in CRITIC_LOSSES and critic is None:
            raise RatError(f"refine-loss '{loss}' climbs π_θ's critic, and none was given; give the critic saved with "
                           "the adversary, or refine with 'l2'")
        self.adversary, self.intention, self.victim, self.threat = adversary, intention, victim, threat
        self.critic = critic
        self.steps, self.lr, self.gaps, self.loss = steps, lr, gaps, loss
        self.switch_gap = switch_gap
        self.device = next(adversary.parameters()).device
        self.previous: dict[int, torch.Tensor] = {}  # per episode slot: the last Δ chosen there, before tanh
        self.contexts: dict[int, object] | None = {} if is_sequence(victim) else None  # per slot: the victim's

    def reset(self, slot: int = 0) -> None:
        """A new episode in ``slot``: its first observation starts from the network's Δ alone."""
        self.previous.pop(slot, None)
        if self.contexts is not None:
            self.contexts[slot] = self.victim.initial_context(1)

    def observe(self, seen: np.ndarray, action: np.ndarray, reward: float, slot: int = 0) -> None:
        """The step just taken in ``slot``'s episode, for a sequence victim's context (nothing for a memoryless one)."""
        if self.contexts is None:
            return
        row = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float32, device=self.device).reshape(1, -1)  # noqa: E731
        self.contexts[slot] = self.victim.update_context(self._context(slot), row(seen), row(action),
                                                         torch.tensor([float(reward)]))

    def _context(self, slot: int):
        if slot not in self.contexts:  # an episode begun without reset()
            self.contexts[slot] = self.victim.initial_context(1)
        return self.contexts[slot]

    def _action(self, s: torch.Tensor, raw: torch.Tensor, context) -> torch.Tensor:
        return self.victim.act(self.threat.perturb(s, torch.tanh(raw)), context)

    def _losses(self, s: torch.Tensor, raw: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor,
                context, loss: str) -> torch.Tensor:
        """Each row's ``loss`` (one per observation; ``context``: a sequence victim's, one row each)."""
        action = self._action(s, raw, context)
        if loss == "q":
            return -torch.min(*self.critic(s, action))
        return (action - mean).pow(2).sum(-1)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.batch(np.asarray(obs)[None], [0])[0]

    @torch.enable_grad()  # its steps follow gradients, even where the caller plays episodes under no_grad
    def batch(self, obs: np.ndarray, slots: Sequence[int]) -> np.ndarray:
        """Δ for each row of ``obs [B, d]``; row i continues the episode in ``slots[i]``."""
        s = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
        mean, log_std = intention_gaussian(self.intention, s)
        packed = None if self.contexts is None else torch.cat(
            [self.victim.pack_context(self._context(slot)) for slot in slots])

        def context(rows=slice(None)):  # a sequence victim's contexts of these rows, prepared to act on at every step
            return None if packed is None else prepared(self.victim, self.victim.unpack_context(packed[rows]))

        rows = list(range(len(s)))
        best = self._refine(s, mean, log_std, slots, rows, context, "l2" if self.loss == "l2-or-q" else self.loss)
        if self.loss == "l2-or-q" or self.gaps is not None:
            with torch.no_grad():
                gap = (self._action(s, best, context()) - mean).norm(dim=-1)
        if self.loss == "l2-or-q":  # refined again by π_θ's critic where π_θ's action is out of reach
            far = [i for i in rows if gap[i] > self.switch_gap]
            if far:
                best[far] = self._refine(s, mean, log_std, slots, far, context, "q")
                with torch.no_grad():
                    gap[far] = (self._action(s[far], best[far], context(far)) - mean[far]).norm(dim=-1)
        if self.gaps is not None:
            self.gaps.extend(gap.tolist())
        for i, slot in enumerate(slots):
            self.previous[slot] = best[i:i + 1]
        return torch.tanh(best).double().cpu().numpy()

    def _refine(self, s: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor, slots: Sequence[int],
                rows: list[int], context, loss: str) -> torch.Tensor:
        """Δ before tanh for the batch's ``rows``: ``steps`` Adam steps on ``loss``, from the network's Δ or the
        Δ chosen at the episode's previous observation, whichever ``loss`` prefers; the best seen."""
        s, mean, log_std = s[rows], mean[rows], log_std[rows]
        with torch.no_grad():
            raw = torch.atanh(self.adversary(s).clamp(-0.999, 0.999))
            known = [i for i, row in enumerate(rows) if slots[row] in self.previous]
            if known:  # the previous Δ where it fits this state better (a tie keeps the network's)
                before = torch.cat([self.previous[slots[rows[i]]] for i in known])
                theirs = context([rows[i] for i in known])
                better = self._losses(s[known], before, mean[known], log_std[known], theirs, loss) < \
                    self._losses(s[known], raw[known], mean[known], log_std[known], theirs, loss)
                raw[known] = torch.where(better[:, None], before, raw[known])
        raw.requires_grad_(True)
        optimizer = torch.optim.Adam([raw], lr=self.lr)
        best, best_loss = raw.detach().clone(), torch.full((len(s),), float("inf"), device=self.device)
        theirs = context(rows)
        for step in range(self.steps + 1):  # the last pass only scores the last step
            losses = self._losses(s, raw, mean, log_std, theirs, loss)
            with torch.no_grad():
                improved = losses < best_loss
                best = torch.where(improved[:, None], raw, best)
                best_loss = torch.where(improved, losses, best_loss)
            if step < self.steps:
                optimizer.zero_grad(set_to_none=True)
                losses.sum().backward(inputs=[raw])
                optimizer.step()
        return best


refined_function = RefinedAttack  # the name callers know: the adversary's Δ, refined at every observation
