"""A robust agent from a victim, in a run directory: :func:`train_robust`; fresh attacks on it: :func:`evaluate_robust`.

The run directory holds what every run of the project holds (``config.json``, ``metrics.csv``, a resumable
``checkpoint``), and at the end the robust agent as a victim (``victim.safetensors`` + ``victim.json``, so
``rat victim eval RUN`` and ``rat attack train --victim RUN`` take it), ``report.json`` and ``training.png``.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym

from rat import seeds
from rat.agents.networks import TanhGaussianActor
from rat.attacks.base import AttackSetup
from rat.attacks.threat import ThreatModel
from rat.envs.targets import TargetBehaviour
from rat.envs.tasks import episode_length
from rat.errors import RatError
from rat.loop import TrainingLoop, write_report
from rat.plots import plot_robust_training
from rat.preferences.offline import reward_source
from rat.robust.adversaries import RATAdversary, ppo_adversary
from rat.robust.trainer import RobustConfig, RobustTrainer, TaskReward, neg_task_reward
from rat.runs import Run, git_commit, seed_everything
from rat.victims.adapters import save_victim
from rat.victims.base import ModuleVictim, Victim, check_compatible, is_sequence


def starting_actor(victim: Victim, config: RobustConfig) -> TanhGaussianActor | None:
    """The actor the agent starts from: a copy of the victim's (``finetune``) or none (``scratch``)."""
    if config.init == "scratch":
        return None
    policy = getattr(victim, "policy", None)
    if not isinstance(policy, TanhGaussianActor):
        raise RatError(f"victim '{victim.name}' is not a SAC actor of this project (zoo:<task>@sac, a victim checkpoint), "
                       "so it cannot be fine-tuned; pass --init scratch to train a robust agent from scratch")
    if (policy.trunk[0].out_features, (len(policy.trunk) - 1) // 2) != (config.sac.hidden, config.sac.layers):
        raise RatError(f"the victim's actor is {(len(policy.trunk) - 1) // 2}×{policy.trunk[0].out_features}, "
                       f"the agent's SAC {config.sac.layers}×{config.sac.hidden}; --set sac.hidden=... sac.layers=... "
                       "to match it")
    return copy.deepcopy(policy).requires_grad_(True).train()


def adversary_for(config: RobustConfig, setup: AttackSetup, adversary_config: Any, run: Run):
    """The phase adversary of ``config.method`` against ``setup.victim`` (None where the method has none)."""
    method = config.adversary_method
    if method is None:
        return None, 1
    if method == "rat":
        from dataclasses import replace

        from rat.attacks.rat import RATConfig, RATTrainer
        from rat.preferences.store import LabelStore

        if not isinstance(adversary_config, RATConfig):
            raise RatError(f"{config.method} trains a RAT adversary: its settings must be a RATConfig")
        # The robust loop evaluates the adversary itself; RAT's own evaluations (its snapshots, and imitate="best",
        # which keeps π_θ as scored there) do not run, so the adversary imitates π_θ as it moves.
        rat_cfg = replace(adversary_config, imitate="current", select="last", seed=config.seed)
        rat_cfg.pebble.check_budget("RAT")
        env = setup.make_env(config.seed)
        trainer = RATTrainer(rat_cfg, setup, env, LabelStore(run.dir / "labels.sqlite"), run.dir.name,
                             run.dir / "snapshots", setup.labeller)
        return RATAdversary(trainer), 1
    reward = neg_task_reward if config.adversary_reward == "neg-task" else reward_source(setup.target, None)
    env = TaskReward(setup.make_env(config.seed))
    return ppo_adversary(method, setup, env, reward, adversary_config), adversary_config.n_steps


def robust_task(victim_spec: str, target: TargetBehaviour, task: str | None = None) -> tuple[Victim, str]:
    """The victim of ``victim_spec`` and its task, checked: the agent trains in that task and the adversary seeks
    ``target`` in the same environment."""
    from rat.experiments.runner import load_victim_for

    victim, task, env_task = load_victim_for(victim_spec, target, task)
    if env_task != task:
        raise RatError(f"target '{target.name}' is sought in {env_task}'s environment, but the agent trains in "
                       f"{task}'s; robust training needs a target of the victim's own environment (e.g. reach)")
    return victim, task


def adversary_settings(config: RobustConfig, preset: str, target: str, budget: int | None = None):
    """The adversary's settings for ``config.method`` under an attack preset: RAT's run long enough for phase 0
    and every later adversary phase (its label schedule spans them all); SA-RL's or PA-AD's PPO."""
    from rat.experiments.runner import attack_config

    method = config.adversary_method
    if method is None:
        return None
    rounds = -(-config.agent_steps // config.phase_steps)
    steps = config.first_adversary_steps + rounds * config.adversary_phase_steps * config.alternates
    extra = {"seed": config.seed} if method == "rat" else {}
    return attack_config(method, preset, budget if method == "rat" else None, steps, target, **extra)


def prepare_robust(config: RobustConfig, victim: Victim, target: TargetBehaviour,
                   make_env: Callable[[int], gym.Env], threat: ThreatModel, out: str | Path,
                   adversary_config: Any = None, describe: dict[str, Any] | None = None,
                   progress: bool = True) -> tuple[Run, RobustTrainer, TrainingLoop]:
    """The run directory, the trainer and its training loop of :func:`train_robust`, not yet started (nor resumed)."""
    describe = dict(describe or {})
    env = make_env(config.seed + seeds.ROBUST)
    check_compatible(victim, env)
    if is_sequence(victim):
        raise RatError(f"robust training makes SAC agents; '{victim.name}' reads its history: pick a SAC victim")
    if config.adversary_method is not None and adversary_config is None:
        raise RatError(f"{config.method} needs the settings of its {config.adversary_method} adversary")
    actor = starting_actor(victim, config)
    seed_everything(config.seed)
    shell = TanhGaussianActor(env.observation_space.shape[0], env.action_space.shape[0], config.sac.hidden,
                              config.sac.layers)  # the frozen victim's module; the agent's weights go in
    frozen = ModuleVictim(shell, victim.observation_space, victim.action_space, name=f"robust-{config.method}",
                          meta=dict(victim.meta))
    setup = AttackSetup(frozen, target, make_env, threat, config.seed,
                        "labels" if config.adversary_method == "rat" else "oracle",
                        describe={**describe, "task": describe.get("task"), "victim_task": describe.get("task")},
                        progress=progress)
    run = Run(out, {"robust": config, "adversary": adversary_config, **describe})
    adversary, unit = adversary_for(config, setup, adversary_config, run)
    trainer = RobustTrainer(config, setup, env, adversary, actor)
    loop = TrainingLoop(run, trainer, trainer.planned_steps(episode_length(env), unit), eval_every=config.eval_every,
                        checkpoint_every=config.checkpoint_every, checkpoint_at_boundary=True,
                        desc=f"{config.method} {target.name}", progress=progress)
    return run, trainer, loop


def train_robust(config: RobustConfig, victim: Victim, target: TargetBehaviour, make_env: Callable[[int], gym.Env],
                 threat: ThreatModel, out: str | Path, adversary_config: Any = None,
                 describe: dict[str, Any] | None = None, progress: bool = True) -> dict[str, Any]:
    """Train a robust agent from ``victim`` in ``make_env``'s task, against ``target`` (resumable from ``out``).

    ``make_env(seed)`` is the victim's own task, whose reward is the agent's; ``adversary_config`` is the
    adversary's settings (a :class:`~rat.attacks.rat.RATConfig` for RAT-ATLA and RAT-WocaR, a
    :class:`~rat.attacks.rl.PPOConfig` for ATLA and PA-ATLA). Returns the report (also ``out/report.json``).
    """
    describe = dict(describe or {})
    run, trainer, loop = prepare_robust(config, victim, target, make_env, threat, out, adversary_config, describe,
                                        progress)
    adversary, horizon = trainer.adversary, episode_length(trainer.env)
    loop.resume()
    loop.run()
    while not trainer.finished:  # episodes ended early (a terminating task): the plan was short
        loop.total = trainer.step + horizon
        loop.run()

    # --- results -------------------------------------------------------------------------------------
    agent = trainer.current_agent()
    detail = final_returns(trainer, agent, config.final_eval_episodes)
    meta = {"task": describe.get("task") or victim.meta.get("task"), "method": f"robust-{config.method}",
            "robust": {"method": config.method, "init": config.init, "started_from": describe.get("victim", victim.name),
                       "target": target.name, "epsilon": threat.epsilon, "norm": threat.norm},
            "config": run.config, "commit": git_commit(), "train_seconds": round(loop.total_seconds, 1)}
    save_victim(run.dir / "victim", agent.policy, victim.observation_space, victim.action_space, meta)
    report = {"method": config.method, "victim": describe.get("victim", victim.name), "task": meta["task"],
              "target": target.name, "epsilon": threat.epsilon, "norm": threat.norm, "seed": config.seed,
              "init": config.init, "agent_steps": trainer.agent_steps, "warmup_steps": trainer.warmup_steps,
              "adversary_steps": adversary.step if adversary is not None else 0, **trainer.counters,
              "train_minutes": round(loop.total_seconds / 60, 2), "episodes": config.final_eval_episodes,
              **detail}
    write_report(run.dir, report)
    plot_robust_training(run.logger.path, run.dir / "training.png",
                         f"{config.method} against {target.name}: {describe.get('victim', victim.name)}")
    return report


def train_robust_from(config: RobustConfig, victim_spec: str, target: str, out: str | Path, preset: str = "cpu",
                      budget: int | None = None, threat: ThreatModel = ThreatModel(), task: str | None = None,
                      adversary_set: tuple[str, ...] = (), progress: bool = True) -> dict[str, Any]:
    """:func:`train_robust` from names, as ``rat robust train`` and ``rat bench table3`` give them: the victim's
    spec, the target's name, the adversary's settings under ``preset`` (with ``budget`` labels for RAT) and
    ``adversary_set``'s ``NAME=VALUE`` changes to them."""
    from rat.configs import parse_assignment, with_values
    from rat.envs import get_target, make_task

    behaviour = get_target(target)
    victim, task = robust_task(victim_spec, behaviour, task)
    adversary_config = adversary_settings(config, preset, target, budget)
    if adversary_set:
        if adversary_config is None:
            which = "rat-wocar with wocar-critic worst-case" if config.method == "rat-wocar" else config.method
            raise RatError(f"{which} trains no adversary; drop --adversary-set")
        adversary_config = with_values(adversary_config, dict(parse_assignment(type(adversary_config), a)
                                                              for a in adversary_set))
    return train_robust(config, victim, behaviour, lambda s: make_task(task, seed=s), threat, out, adversary_config,
                        describe={"victim": victim_spec, "task": task}, progress=progress)


def final_returns(trainer: RobustTrainer, agent: ModuleVictim, episodes: int) -> dict[str, Any]:
    """Table 3's numbers for ``agent``: task return (mean, std) and success clean, the target's success clean, and
    the same under the run's own final adversary (its mean Δ), all on the final episodes."""
    from rat.attacks.evaluation import evaluate_attack, evaluate_clean
    from rat.eval import evaluate
    from rat.victims.base import numpy_policy

    s, seed = trainer.setup, trainer.config.seed + seeds.EVAL_ENV
    clean = evaluate(numpy_policy(agent), s.make_env(seed), episodes, seeds.FINAL)
    aimed = evaluate_clean(agent, s.make_env(seed), s.target, episodes, seeds.FINAL)
    out = {"clean_return": clean.mean_return, "clean_return_std": clean.std_return,
           "clean_task_success": clean.success_rate, "clean_target_success": aimed.success_rate}
    if trainer.adversary is not None:
        attacked = evaluate_attack(agent, trainer.adversary.perturbation(sample=False), s.make_env(seed), s.target,
                                   s.threat, episodes, seeds.FINAL)
        out |= {"own_adversary_return": attacked.result.mean_return,
                "own_adversary_return_std": attacked.result.std_return,
                "own_adversary_target_success": attacked.result.success_rate}
    return out


def attack_agent(victim_spec: str, out: str | Path, target: str, threat: ThreatModel, attacks: list[str],
                 preset: str = "cpu", budget: int | None = None, episodes: int = 100, seed: int = 0,
                 progress: bool = True) -> dict[str, Any]:
    """Each attack of ``attacks`` trained afresh against ``victim_spec`` in ``out/<attack>`` with ``preset``'s settings
    (resumable; a finished one is not trained again), then ``episodes`` attacked episodes (kept in
    ``out/<attack>/table-row.json``). RAT learns from labels; SA-RL and PA-AD from the target's oracle reward.

    Returns table 3's cells: per attack the task return (mean, std) and the target's success, and the clean return."""
    from rat.attacks.base import get_attack, measured_reward
    from rat.experiments.runner import attack_config, attack_setup, evaluate_saved_attack, train_attack

    rows = {}
    for method in attacks:
        directory = Path(out) / method
        cached = directory / "table-row.json"
        if cached.exists():
            rows[method] = json.loads(cached.read_text())
            continue
        attack = get_attack(method)
        reward = measured_reward(attack)
        if not (directory / "report.json").exists():
            setup = attack_setup(victim_spec, target, threat, seed, reward, progress=progress)
            train_attack(method, setup, attack_config(method, preset, budget, None, target), directory)
        result = evaluate_saved_attack(directory, episodes, seed, progress=progress)
        res, clean = result["attack"].result, result["clean"]  # clean: the same episodes unattacked
        rows[method] = {"reward": reward, "return": res.mean_return, "return_std": res.std_return,
                        "target_success": res.success_rate, "episodes": res.episodes,
                        "clean_return": clean.mean_return, "clean_return_std": clean.std_return,
                        "clean_target_success": clean.success_rate}
        cached.write_text(json.dumps(rows[method], indent=1))
    first = next(iter(rows.values()), None)
    return {"victim": victim_spec, "target": target, "attacks": rows,
            "clean_return": first["clean_return"] if first else None,
            "clean_return_std": first["clean_return_std"] if first else None}


def finished_report(run: str | Path) -> dict[str, Any]:
    """The report of the finished robust agent in ``run`` (a clear error where it has not finished)."""
    path = Path(run) / "report.json"
    if not path.exists():
        raise RatError(f"'{run}' holds no finished robust agent (no report.json); finish it with the same "
                       "`rat robust train ... --out` command")
    return json.loads(path.read_text())


def evaluate_robust(run: str | Path, attacks: list[str], preset: str = "cpu", budget: int | None = None,
                    episodes: int = 100, seed: int = 0, progress: bool = True) -> dict[str, Any]:
    """Fresh attacks on the robust agent of ``run`` (:func:`attack_agent` in ``run/eval``); the table is also
    written to ``run/eval/table.json``."""
    run = Path(run)
    report = finished_report(run)
    table = attack_agent(str(run), run / "eval", report["target"], ThreatModel(report["epsilon"], report["norm"]),
                         attacks, preset, budget, episodes, seed, progress)
    table = {"run": str(run), "method": report["method"], **table}
    if table["clean_return"] is None:
        table |= {"clean_return": report["clean_return"], "clean_return_std": report["clean_return_std"]}
    (run / "eval").mkdir(exist_ok=True)
    (run / "eval" / "table.json").write_text(json.dumps(table, indent=1))
    return table
