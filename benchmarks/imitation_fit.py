"""Can imitating π_θ make the victim do it? RAT's inner level, offline, with the imitated policy frozen.

A RAT run imitates a moving intention policy on a growing buffer; this script takes both out of
the loop. From a run directory (``rat attack train`` or ``rat intention train``) it loads the
replay buffer and an intention policy — the π_θ a RAT run imitated last (``imitate=best``), else
the run's current actor — fits a fresh adversary to it with RAT's inner loss (unit weights), and
reports:

- the imitation gap ‖μ_ν(s̃) − tanh μ_θ(s)‖ on held-out recent states, as the fit goes;
- the gap per state when Δ itself is optimised (no network): what the ε-ball allows at all;
- the attack's success over fresh episodes of the target, and π_θ's own success there;
- with ``--rounds K``, the same fit closed on the attacked victim's own states, DAgger-style: K times,
  the attacked episodes' states join the pool and the adversary trains ``--round-updates`` more (the
  shift RAT's combined behaviour policy exists to close, here closed directly).

    python benchmarks/imitation_fit.py RUN_DIR --victim zoo:drawer-open-v3 --target reach
    python benchmarks/imitation_fit.py RUN_DIR --victim zoo:drawer-open-v3 --target reach --updates 20000 --recent 50000
    python benchmarks/imitation_fit.py RUN_DIR --victim zoo:drawer-open-v3 --target reach --rounds 5

Results are recorded in ``docs/notes/strength-log.md``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from rat.agents.networks import TanhGaussianActor
from rat.attacks.evaluation import evaluate_attack
from rat.attacks.losses import Adversary, Imitation, inner_loss
from rat.attacks.refine import refined_function
from rat.attacks.saved import adversary_function
from rat.attacks.threat import ThreatModel
from rat.checkpoint import load_checkpoint
from rat.envs import make_task
from rat.envs.targets import get_target
from rat.errors import RatError
from rat.eval import evaluate
from rat.victims import load_victim
from rat.victims.base import Victim


def imitated_actor(state: dict) -> TanhGaussianActor:
    """π_θ as the run's adversary imitated it last: the kept copy (imitate=best), else the current actor."""
    agent = state["learner"]["agent"]
    weights = state["best"]["actor"] if "best" in state else {
        k.removeprefix("actor."): v for k, v in agent.items() if k.startswith("actor.")}
    return TanhGaussianActor.from_state_dict(weights).requires_grad_(False)


def ball_gap(victim: Victim, objective: Imitation, obs: torch.Tensor, steps: int = 200) -> torch.Tensor:
    """Per state, the smallest imitation gap Adam on Δ (through tanh, so inside the ball) finds: ``[B, act_dim]``.

    Not :func:`rat.attacks.gradient.search_ball`: its signed steps of fixed size are the attack's PGD, and
    as a bound they are looser here (a gap of 1.01 where Adam finds 0.79, same 512 states, 200 steps).
    """
    target = torch.tanh(objective.intention.distribution_params(obs)[0])
    raw = torch.zeros_like(obs, requires_grad=True)
    optimizer = torch.optim.Adam([raw], lr=0.1)
    for _ in range(steps):
        action = victim.act(objective.threat.perturb(obs, torch.tanh(raw)))
        loss = ((action - target) ** 2).sum(-1).mean()
        optimizer.zero_grad()
        loss.backward(inputs=[raw])
        optimizer.step()
    with torch.no_grad():
        return (victim.act(objective.threat.perturb(obs, torch.tanh(raw))) - target).abs()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a RAT or intention run directory (its checkpoint)")
    parser.add_argument("--victim", required=True, help="the victim the run attacked, e.g. zoo:drawer-open-v3")
    parser.add_argument("--task", help="its task (default: the victim's)")
    parser.add_argument("--target", default="reach")
    parser.add_argument("--epsilon", type=float, default=0.1)
    parser.add_argument("--updates", type=int, default=20_000)
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--recent", type=int, default=20_000, help="train on the buffer's last N states")
    parser.add_argument("--deterministic", action="store_true", help="train with Δ's mean (no exploration noise)")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--mean-reg", type=float, default=0.0, help="weight of a penalty on Δ's pre-tanh mean, squared")
    parser.add_argument("--online-steps", type=int, default=0,
                        help="also attack with Δ refined per observation by this many Adam steps towards π_θ's action")
    parser.add_argument("--rounds", type=int, default=0, help="then add the attacked episodes' states and refit, K times")
    parser.add_argument("--round-updates", type=int, default=5_000, help="updates after each round's states join")
    args = parser.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)

    try:
        state, _ = load_checkpoint(args.run / "checkpoint")
        victim = load_victim(args.victim)
    except RatError as exc:
        parser.error(str(exc))
    if "learner" not in state:
        parser.error(f"'{args.run}' is not a RAT or intention run (its checkpoint has no intention policy)")
    obs_all = torch.as_tensor(state["learner"]["buffer"]["obs"]).float()
    pool = obs_all[-args.recent:]
    held = obs_all[torch.randint(max(0, len(obs_all) - 20_000), len(obs_all), (1024,))]
    actor = imitated_actor(state)
    objective = Imitation(victim, actor, None, torch.tensor(0.0), ThreatModel(args.epsilon, "linf"))

    adversary = Adversary(obs_all.shape[1])
    optimizer = torch.optim.Adam(adversary.parameters(), lr=args.lr)
    start = time.time()

    def fit(pool: torch.Tensor, updates: int) -> None:
        for update in range(1, updates + 1):
            obs = pool[torch.randint(0, len(pool), (args.batch,))]
            noise = None if args.deterministic else torch.randn_like(obs)
            loss = inner_loss(torch.ones(args.batch), objective.kl(adversary, None, obs, noise))
            if args.mean_reg:
                loss = loss + args.mean_reg * adversary.policy.distribution_params(obs)[0].pow(2).mean()
            optimizer.zero_grad(set_to_none=True)
            loss.backward(inputs=list(adversary.parameters()))
            optimizer.step()
            if update % max(1, updates // 5) == 0:
                with torch.no_grad():
                    saturated = (adversary(held).abs() > 0.99).float().mean().item()
                print(f"update {update}: loss {loss.item():.3f}, gap on held-out states "
                      f"{objective.gap(adversary, held):.3f}, Δ saturated (|Δ_i| > 0.99) {saturated:.1%} "
                      f"({time.time() - start:.0f} s)", flush=True)

    fit(pool, args.updates)
    per_dim = ball_gap(victim, objective, held[:512])
    print(f"what the ball allows (Δ optimised per state, 512 states): gap {per_dim.norm(dim=-1).mean():.3f}, "
          f"per dimension {[round(float(x), 3) for x in per_dim.mean(0)]}")
    target = get_target(args.target)
    task = target.env_task(args.task or victim.meta["task"])
    threat = objective.threat
    attack = evaluate_attack(victim, adversary_function(adversary), make_task(task, seed=1), target, threat,
                             args.episodes, 1000)
    print(f"attack success: {attack.result.success_rate:.1%} over {args.episodes} episodes")

    if args.online_steps:
        gaps: list[float] = []
        online = refined_function(adversary, actor, victim, threat, args.online_steps, gaps=gaps)
        attack = evaluate_attack(victim, online, make_task(task, seed=1), target, threat, args.episodes, 1000)
        print(f"attack success with Δ refined per observation ({args.online_steps} Adam steps, gap left "
              f"{np.mean(gaps):.3f}): {attack.result.success_rate:.1%} over {args.episodes} episodes", flush=True)

    for k in range(1, args.rounds + 1):  # DAgger: the attacked victim's states join the pool
        seen: list[np.ndarray] = []
        delta = adversary_function(adversary)

        def recording(obs: np.ndarray, seen=seen, delta=delta) -> np.ndarray:
            seen.append(np.array(obs, dtype=np.float32))
            return delta(obs)

        # other episodes than the yardstick's (seed 1000)
        evaluate_attack(victim, recording, make_task(task, seed=k), target, threat, args.episodes, 5000 + 100 * k)
        visited = torch.as_tensor(np.stack(seen))
        allowed = ball_gap(victim, objective, visited[torch.randperm(len(visited))[:512]]).norm(dim=-1).mean()
        print(f"round {k}: gap on the attacked victim's states {objective.gap(adversary, visited):.3f} "
              f"(the ball allows {allowed:.3f} there), on held-out ones {objective.gap(adversary, held):.3f}", flush=True)
        pool = torch.cat([pool, visited])
        fit(pool, args.round_updates)
        attack = evaluate_attack(victim, adversary_function(adversary), make_task(task, seed=1), target, threat,
                                 args.episodes, 1000)
        print(f"round {k} ({len(pool)} states): attack success {attack.result.success_rate:.1%} "
              f"over {args.episodes} episodes", flush=True)

    @torch.no_grad()
    def intention(obs: np.ndarray) -> np.ndarray:
        return actor(torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)).squeeze(0).numpy()

    alone = evaluate(intention, make_task(task, seed=1), args.episodes, 1000, target=target)
    print(f"π_θ alone: {alone.success_rate:.1%} over {args.episodes} episodes")


if __name__ == "__main__":
    main()
