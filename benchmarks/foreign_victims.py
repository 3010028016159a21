"""Victims this project did not make: Stable-Baselines3 SAC, TD3 and PPO agents on Meta-World v3 tasks outside
the paper's eight, trained with SB3's own defaults and nothing of ours, to measure attacks and `rat audit` on.

Each agent trains until an evaluation (every ``--eval-every`` steps, 10 episodes, deterministic actions) succeeds
in every episode, or for its step budget; it is then saved with SB3's ``model.save`` and scored over 20 episodes
through rat's own loader (``load_sb3_victim``, the file read as a user's would be). ``victims.json`` records each
agent's clean success, return, steps and minutes, and whether it is **held out** of any tuning.

    OMP_NUM_THREADS=1 python benchmarks/foreign_victims.py --out benchmarks/foreign          # all of them
    python benchmarks/foreign_victims.py --only door-close-v3-sac --out benchmarks/foreign   # one

A finished agent is kept and not retrained. An agent interrupted mid-training starts again (resuming would mean
``SAC.load``, which unpickles; this project never loads a pickle).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path


@dataclass(frozen=True)
class Foreign:
    name: str  #: the file's stem: <task>-<algorithm>
    task: str  #: a Meta-World v3 task outside the paper's eight
    algorithm: str  #: sac, td3 or ppo (Stable-Baselines3)
    steps: int  #: the step budget
    held_out: bool = False  #: never used to choose a setting or a default


VICTIMS = (
    Foreign("door-close-v3-sac", "door-close-v3", "sac", 100_000),
    Foreign("button-press-topdown-v3-td3", "button-press-topdown-v3", "td3", 150_000),
    Foreign("reach-v3-ppo", "reach-v3", "ppo", 1_000_000),
    Foreign("handle-press-v3-sac", "handle-press-v3", "sac", 150_000, held_out=True),
)


def model_for(victim: Foreign, env, seed: int):
    """SB3's model with its own defaults (a 256×256 actor and critic for the off-policy two, PPO's 64×64)."""
    import stable_baselines3 as sb3

    if victim.algorithm == "ppo":
        return sb3.PPO("MlpPolicy", env, seed=seed, verbose=0)
    cls = {"sac": sb3.SAC, "td3": sb3.TD3}[victim.algorithm]
    return cls("MlpPolicy", env, seed=seed, verbose=0, policy_kwargs={"net_arch": [256, 256]})


def success_rate(policy, task: str, episodes: int, seed: int) -> tuple[float, float]:
    """Task success and mean return of ``policy`` (obs -> action) over ``episodes`` episodes."""
    from rat.envs import make_task
    from rat.eval import evaluate

    result = evaluate(policy, make_task(task, seed), episodes, seed)
    return result.success_rate, result.mean_return


def train(victim: Foreign, out: Path, seed: int, eval_every: int, steps: int | None = None) -> dict:
    """Train ``victim``, save ``<out>/<name>.zip``, and return its record."""
    from stable_baselines3.common.callbacks import BaseCallback

    from rat.envs import make_task
    from rat.victims import load_sb3_victim
    from rat.victims.base import numpy_policy

    budget = steps or victim.steps
    model = model_for(victim, make_task(victim.task, seed), seed)
    history = []

    class EvaluateAndStop(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps % eval_every:
                return True
            act = lambda obs: model.predict(obs, deterministic=True)[0]  # noqa: E731
            rate, mean_return = success_rate(act, victim.task, 10, seed + 10**6 + self.num_timesteps)
            history.append({"step": self.num_timesteps, "success": rate, "return": mean_return})
            print(f"{victim.name}: {self.num_timesteps} steps, success {rate:.0%}, return {mean_return:.0f}", flush=True)
            return rate < 1.0

    t0 = time.perf_counter()
    model.learn(total_timesteps=budget, callback=EvaluateAndStop())
    minutes = (time.perf_counter() - t0) / 60
    path = out / f"{victim.name}.zip"
    model.save(path)
    rate, mean_return = success_rate(numpy_policy(load_sb3_victim(path)), victim.task, 20, seed + 2 * 10**6)
    return asdict(victim) | {"seed": seed, "trained_steps": model.num_timesteps, "train_minutes": round(minutes, 1),
                             "clean_success": rate, "clean_return": mean_return, "episodes": 20,
                             "file": path.name, "history": history}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/foreign"))
    parser.add_argument("--only", default="", help="comma-separated names (default: all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-every", type=int, default=10_000)
    parser.add_argument("--steps", type=int, default=None, help="override every agent's step budget (a check)")
    args = parser.parse_args(argv)
    chosen = [v for v in VICTIMS if not args.only or v.name in args.only.split(",")]
    unknown = set(filter(None, args.only.split(","))) - {v.name for v in VICTIMS}
    if unknown:
        parser.error(f"unknown victim(s) {', '.join(sorted(unknown))}; choose from {', '.join(v.name for v in VICTIMS)}")
    args.out.mkdir(parents=True, exist_ok=True)
    record_path = args.out / "victims.json"
    records = json.loads(record_path.read_text()) if record_path.exists() else {}
    for victim in chosen:
        if victim.name in records and (args.out / records[victim.name]["file"]).exists():
            print(f"{victim.name}: trained already ({records[victim.name]['clean_success']:.0%} clean success)")
            continue
        records[victim.name] = train(victim, args.out, args.seed, args.eval_every, args.steps)
        record_path.write_text(json.dumps(records, indent=1) + "\n")  # after each agent: nothing finished is lost
        print(f"{victim.name}: clean success {records[victim.name]['clean_success']:.0%} over 20 episodes")
    return records


if __name__ == "__main__":
    main()
