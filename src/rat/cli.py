"""The ``rat`` command line. Every user mistake ends in one line on stderr and exit code 2."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from rat.errors import RatError


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="rat")
def cli() -> None:
    """Targeted behaviour attacks on deep RL agents (RAT), and the victims they attack."""


# --- listings ------------------------------------------------------------------------------------


@cli.group("list")
def list_group() -> None:
    """List tasks, target behaviours and zoo victims."""


@list_group.command("tasks")
@click.option("--all", "show_all", is_flag=True, help="every Meta-World v3 task, not only the paper's eight")
def list_tasks(show_all: bool) -> None:
    """Meta-World v3 tasks (the paper's eight, with their opposites and zoo victims)."""
    from rat.envs import PAPER_TASKS, all_tasks
    from rat.victims import zoo_tasks

    zoo = set(zoo_tasks())
    click.echo(f"{'task':<18} {'opposite':<18} zoo victim")
    for task, opposite in sorted(PAPER_TASKS.items()):
        click.echo(f"{task:<18} {opposite:<18} {'zoo:' + task if task in zoo else '-'}")
    if show_all:
        click.echo("\nall Meta-World v3 tasks: " + ", ".join(all_tasks()))


@list_group.command("targets")
def list_targets() -> None:
    """Registered target behaviours."""
    from rat.envs import list_targets as targets

    for t in targets():
        click.echo(f"{t.name:<10} {t.description}")


# --- victims ---------------------------------------------------------------------------------------


@cli.group()
def victim() -> None:
    """Train, evaluate and regenerate victims."""


def _victim_config(task, method, seed, demo_episodes, bc_updates, total_steps, eval_episodes):
    from rat.envs import check_task
    from rat.victims.training import VictimConfig

    check_task(task)
    return VictimConfig(task=task, method=method, seed=seed, demo_episodes=demo_episodes, bc_updates=bc_updates,
                        total_steps=total_steps, eval_episodes=eval_episodes)


_method_help = "bc: behaviour cloning of the scripted expert (minutes); sac-demo: SAC warm-started with " \
               "demonstrations; sac: SAC from scratch, the paper's way (hours)"


@victim.command("train")
@click.option("--task", required=True, help="Meta-World v3 task, e.g. drawer-open-v3")
@click.option("--method", type=click.Choice(["bc", "sac-demo", "sac"]), default="bc", show_default=True, help=_method_help)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--demo-episodes", type=int, default=100, show_default=True, help="expert episodes (bc, sac-demo)")
@click.option("--bc-updates", type=int, default=20_000, show_default=True, help="behaviour-cloning gradient steps")
@click.option("--total-steps", type=int, default=1_000_000, show_default=True, help="SAC environment steps")
@click.option("--eval-episodes", type=int, default=50, show_default=True, help="final clean evaluation episodes")
@click.option("--out", type=click.Path(path_type=Path), default=None, help="run directory [runs/victim-<task>-<method>-<seed>]")
@click.option("--tensorboard", is_flag=True, help="also log to TensorBoard (needs the 'tensorboard' extra)")
def victim_train(task, method, seed, demo_episodes, bc_updates, total_steps, eval_episodes, out, tensorboard) -> None:
    """Train a victim. Re-running with the same --out resumes an interrupted run."""
    from rat.victims.training import train_victim

    config = _victim_config(task, method, seed, demo_episodes, bc_updates, total_steps, eval_episodes)
    out = out or Path("runs") / f"victim-{task}-{method}-{seed}"
    path, result = train_victim(config, out, progress=True, tensorboard=tensorboard)
    click.echo(f"victim: {path}.safetensors")
    click.echo(f"clean evaluation on {task}: {result.summary()}")


@victim.command("eval")
@click.argument("victim_spec", metavar="VICTIM")
@click.option("--task", default=None, help="environment task [the victim's own, from its metadata]")
@click.option("--target", default="task", show_default=True,
              help="whose success to count: 'task' (the victim's own), 'reach', 'opposite' or a registered one")
@click.option("--episodes", type=int, default=50, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--video", type=click.Path(path_type=Path), default=None, help="write the first episodes to this .mp4/.gif")
@click.option("--video-episodes", type=int, default=2, show_default=True)
@click.option("--json", "as_json", is_flag=True, help="print the result as JSON")
def victim_eval(victim_spec, task, target, episodes, seed, video, video_episodes, as_json) -> None:
    """Evaluate VICTIM (zoo:<task>, an SB3 .zip, or a victim checkpoint) without attack."""
    from rat.envs import check_task, get_target, make_task
    from rat.eval import evaluate
    from rat.victims import check_compatible, load_victim
    from rat.victims.base import numpy_policy

    if episodes <= 0:
        raise RatError(f"--episodes must be positive, got {episodes}")
    behaviour = get_target(target)
    v = load_victim(victim_spec)
    task = task or getattr(v, "meta", {}).get("task")
    if task is None:
        raise RatError(f"victim '{victim_spec}' does not record its task; pass --task")
    env_task = check_task(behaviour.env_task(check_task(task)))
    env = make_task(env_task, seed=seed, render_mode="rgb_array" if video else None)
    check_compatible(v, env, f"task '{env_task}'")
    result = evaluate(numpy_policy(v), env, episodes, seed=seed, target=behaviour, video=video,
                      video_episodes=video_episodes, progress=True)
    if as_json:
        click.echo(json.dumps({"victim": victim_spec, "task": env_task, "target": target, **result.to_dict()}))
    else:
        click.echo(f"{victim_spec} on {env_task}, target '{target}': {result.summary()}")
        if video:
            click.echo(f"video: {video}")


@victim.command("zoo")
@click.option("--task", "tasks", multiple=True, help="only these tasks (repeatable) [the paper's eight]")
@click.option("--jobs", type=int, default=2, show_default=True, help="parallel processes")
@click.option("--dest", type=click.Path(path_type=Path), default=None, help="zoo folder [the package's zoo]")
@click.option("--work-dir", type=click.Path(path_type=Path), default=Path("runs/zoo"), show_default=True)
@click.option("--demo-episodes", type=int, default=100, show_default=True, help="expert episodes per task")
@click.option("--bc-updates", type=int, default=20_000, show_default=True, help="behaviour-cloning steps per task")
@click.option("--eval-episodes", type=int, default=50, show_default=True, help="clean evaluation episodes per task")
def victim_zoo(tasks, jobs, dest, work_dir, demo_episodes, bc_updates, eval_episodes) -> None:
    """Regenerate the victim zoo (behaviour cloning, default settings) and record the timings."""
    from rat.envs import check_task
    from rat.victims.training import VictimConfig
    from rat.victims.zoo import ZOO_DIR, regenerate_zoo

    for t in tasks:
        check_task(t)
    if jobs <= 0:
        raise RatError(f"--jobs must be positive, got {jobs}")

    def report(row):
        click.echo(f"{row['task']:<18} {row['minutes']:5.1f} min  clean success {row['clean_success']:.0%} "
                   f"over {row['episodes']} episodes")

    config = VictimConfig(method="bc", demo_episodes=demo_episodes, bc_updates=bc_updates, eval_episodes=eval_episodes)
    regenerate_zoo(config, list(tasks) or None, work_dir, dest or ZOO_DIR, jobs, on_done=report)


# --- intention policies and labels -------------------------------------------------------------


@cli.group()
def intention() -> None:
    """Learn a target behaviour from preference labels (PEBBLE), without a victim."""


@intention.command("train")
@click.option("--task", default="drawer-open-v3", show_default=True, help="the victim's task (sets the environment)")
@click.option("--target", default="reach", show_default=True, help="target behaviour: reach, opposite, or a registered one")
@click.option("--budget", type=int, default=3000, show_default=True, help="preference queries in all")
@click.option("--steps", type=int, default=100_000, show_default=True, help="environment steps")
@click.option("--per-round", type=int, default=128, show_default=True, help="queries per round")
@click.option("--every", type=int, default=5000, show_default=True, help="steps between query rounds")
@click.option("--strategy", default="disagreement", show_default=True,
              help="query strategy: uniform, disagreement, entropy, kcenter, kcenter-disagreement, kcenter-entropy")
@click.option("--seed-steps", type=int, default=1000, show_default=True, help="uniform random steps first")
@click.option("--pretrain-steps", type=int, default=9000, show_default=True,
              help="state-entropy pre-training steps; the first query round follows")
@click.option("--batch-size", type=int, default=1024, show_default=True, help="SAC batch size")
@click.option("--reward-epochs", type=int, default=200, show_default=True, help="reward-model epochs per round, at most")
@click.option("--eval-every", type=int, default=10_000, show_default=True, help="steps between evaluations")
@click.option("--oracle", is_flag=True, help="learn from the true target reward, no labels (an upper bound)")
@click.option("--teacher-mistake", type=float, default=0.0, show_default=True, help="scripted teacher's mistake rate")
@click.option("--teacher-beta", type=float, default=None, help="Boltzmann rationality (default: perfectly rational)")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--out", type=click.Path(path_type=Path), default=None, help="run directory [runs/intention-...]")
@click.option("--tensorboard", is_flag=True, help="also log to TensorBoard")
def intention_train(task, target, budget, steps, per_round, every, strategy, seed_steps, pretrain_steps, batch_size,
                    reward_epochs, eval_every, oracle, teacher_mistake, teacher_beta, seed, out, tensorboard) -> None:
    """Train an intention policy for TARGET from scripted preference labels; resumes with the same --out."""
    from dataclasses import replace

    from rat.preferences.intention import IntentionConfig, train_intention
    from rat.preferences.pebble import PebbleConfig
    from rat.preferences.reward_model import RewardModelConfig
    from rat.preferences.teacher import TeacherConfig

    base = PebbleConfig()
    pebble = PebbleConfig(sac=replace(base.sac, batch_size=batch_size), budget=budget, per_round=per_round,
                          feedback_every=every, strategy=strategy, seed_steps=seed_steps,
                          unsupervised_steps=pretrain_steps, oracle=oracle, reward=RewardModelConfig(max_epochs=reward_epochs),
                          teacher=TeacherConfig(beta=teacher_beta, mistake=teacher_mistake))
    config = IntentionConfig(task=task, target=target, seed=seed, total_steps=steps, pebble=pebble,
                             eval_every=eval_every)
    out = out or Path("runs") / f"intention-{task}-{target}-{budget}-{seed}"
    report = train_intention(config, out, progress=True, tensorboard=tensorboard)
    lo, hi = report["target_success_ci"]
    click.echo(f"target success of the intention policy: {100 * report['target_success_rate']:.1f}% "
               f"(95% CI {100 * lo:.1f}-{100 * hi:.1f}%, {report['final_eval_episodes']} episodes)")
    click.echo(f"learned reward: preference accuracy {100 * report['preference_accuracy']:.1f}% on "
               f"{report['held_out_pairs']} held-out pairs; Pearson r with the true reward {report['reward_pearson']:.2f}")
    click.echo(f"labels: {report['labels']} of {report['queries_asked']} queries asked; run: {out} "
               "(report.json, reward_quality.png, training.png, labels.sqlite)")


@cli.group()
def labels() -> None:
    """List, export and import preference labels (SQLite label stores)."""


def _open_store(path: Path):
    from rat.preferences.store import LabelStore

    if not path.exists():
        raise RatError(f"no label store at '{path}'; a run keeps its labels in <run>/labels.sqlite")
    return LabelStore(path)


@labels.command("list")
@click.argument("store", type=click.Path(path_type=Path))
@click.option("--source", default=None, help="only this run's labels")
@click.option("--show", type=int, default=10, show_default=True, help="labels to print")
def labels_list(store, source, show) -> None:
    """Summarise the labels in STORE and print the first few."""
    with _open_store(store) as s:
        for src, n in s.sources():
            rounds = s.rounds(src)
            click.echo(f"{src}: {n} labels, {sum(r['asked'] for r in rounds)} queries asked in {len(rounds)} rounds")
        labels = s.read(source)
        for row in labels.rows[:show]:
            who = row["labeller"].get("type", "?")
            click.echo(f"  #{row['id']:<6} {row['created_at']}  {row['task']}/{row['target']}  round {row['round']}  "
                       f"label {row['label']:.1f}  by {who}")


@labels.command("export")
@click.argument("store", type=click.Path(path_type=Path))
@click.argument("dest", type=click.Path(path_type=Path))
@click.option("--source", default=None, help="only this run's labels")
def labels_export(store, dest, source) -> None:
    """Copy the labels of STORE into a new store file DEST."""
    with _open_store(store) as s:
        click.echo(f"exported {s.export_to(dest, source)} labels to {dest}")


@labels.command("import")
@click.argument("store", type=click.Path(path_type=Path))
@click.argument("src", type=click.Path(path_type=Path))
@click.option("--source", default=None, help="file the imported labels under this source name")
def labels_import(store, src, source) -> None:
    """Add every label of store file SRC to STORE (created if missing)."""
    from rat.preferences.store import LabelStore

    with LabelStore(store) as s:
        click.echo(f"imported {s.import_from(src, source)} labels into {store}")


# --- attacks ---------------------------------------------------------------------------------------


@cli.group()
def attack() -> None:
    """Train and evaluate targeted behaviour attacks: RAT and its baselines."""


@attack.command("train")
@click.option("--victim", "victim_spec", default="zoo:drawer-open-v3", show_default=True,
              help="zoo:<task>, a Stable-Baselines3 .zip, or a victim checkpoint")
@click.option("--target", default="reach", show_default=True,
              help="reach (manipulation scenario), opposite (opposite behaviour), or a registered target")
@click.option("--epsilon", type=float, default=0.1, show_default=True, help="budget, raw observation units")
@click.option("--norm", type=click.Choice(["linf", "l2", "l1", "l1-rescale"]), default="linf", show_default=True)
@click.option("--budget", type=int, default=3000, show_default=True, help="preference labels (queries) in all")
@click.option("--preset", type=click.Choice(["cpu", "paper"]), default="cpu", show_default=True,
              help="cpu: 5e4 steps, batches of 256 (this machine); paper: 1e6 steps, batch 1024 (a GPU)")
@click.option("--steps", type=int, default=None, help="environment steps [the preset's]")
@click.option("--ablation", type=click.Choice(["none", "no-weighting", "no-combined", "no-intention"]), default="none",
              show_default=True, help="the paper's table 4 (see the README)")
@click.option("--kl-form", type=click.Choice(["exact", "released"]), default="exact", show_default=True)
@click.option("--hypergradient", type=click.Choice(["exact", "batch-mean"]), default="exact", show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--out", type=click.Path(path_type=Path), default=None, help="run directory [runs/attack-...]")
@click.option("--video/--no-video", default=True, show_default=True,
              help="film two of ten attacked episodes, those reaching the target first")
@click.option("--tensorboard", is_flag=True)
def attack_train(victim_spec, target, epsilon, norm, budget, preset, steps, ablation, kl_form, hypergradient, seed, out,
                 video, tensorboard) -> None:
    """Train a RAT adversary; re-running with the same --out resumes an interrupted run."""
    from rat.attacks.presets import film_attack, rat_config, train_attack

    config = rat_config(preset, budget, steps, target, epsilon=epsilon, norm=norm, seed=seed, ablation=ablation,
                        kl_form=kl_form, hypergradient=hypergradient)
    out = out or Path("runs") / f"attack-{victim_spec.replace(':', '-').replace('/', '_')}-{target}-{seed}"
    report = train_attack(victim_spec, target, config, out, progress=True, tensorboard=tensorboard)
    lo, hi = report["attack_success_ci"]
    click.echo(f"attack success: {100 * report['attack_success_rate']:.1f}% (95% CI {100 * lo:.1f}-{100 * hi:.1f}%, "
               f"{report['episodes']} episodes), {report['labels']} labels, {report['steps']} steps; "
               f"max perturbation {report['max_perturbation']:.4f} <= epsilon {epsilon:g} ({norm})")
    if video:
        filmed = film_attack(out, out / "attack.mp4", seed=seed)
        click.echo(f"video of two of ten attacked episodes, those reaching the target first: {out / 'attack.mp4'} "
                   f"({sum(filmed)}/{len(filmed)} filmed reach the target)")
    click.echo(f"plot of success over training: {out / 'training.png'}; report: {out / 'report.json'}")


@attack.command("baseline")
@click.option("--method", type=click.Choice(["random", "sa-rl", "pa-ad", "mad"]), required=True,
              help="random, SA-RL (PPO in the state-adversarial MDP), PA-AD (PPO director + gradient actor), MAD")
@click.option("--victim", "victim_spec", default="zoo:drawer-open-v3", show_default=True,
              help="zoo:<task>, a Stable-Baselines3 .zip, or a victim checkpoint")
@click.option("--target", default="reach", show_default=True, help="reach, opposite, or a registered target")
@click.option("--epsilon", type=float, default=0.1, show_default=True, help="budget, raw observation units")
@click.option("--norm", type=click.Choice(["linf", "l2", "l1", "l1-rescale"]), default="linf", show_default=True)
@click.option("--labels", "labels_path", type=click.Path(path_type=Path), default=None,
              help="SA-RL/PA-AD learn r̂ from exactly these labels (e.g. a RAT run's labels.sqlite); "
                   "without it they use the true target reward (the oracle variants)")
@click.option("--preset", type=click.Choice(["cpu", "paper"]), default="cpu", show_default=True,
              help="PPO budget: cpu 5e4 steps; paper 1e6 steps at table 6's settings")
@click.option("--steps", type=int, default=None, help="environment steps [the preset's]")
@click.option("--actor-steps", type=int, default=1, show_default=True, help="PA-AD actor: 1 = FGSM, more = PGD")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--out", type=click.Path(path_type=Path), default=None, help="run directory [runs/<method>-...]")
def attack_baseline(method, victim_spec, target, epsilon, norm, labels_path, preset, steps, actor_steps, seed, out):
    """Train (SA-RL, PA-AD) or set up (random, MAD) a baseline attack and evaluate it over 30 episodes."""
    from rat.attacks.baselines import ppo_preset
    from rat.attacks.presets import train_baseline_attack

    variant = "" if method not in ("sa-rl", "pa-ad") else ("-oracle" if labels_path is None else "-labels")
    out = out or Path("runs") / f"{method}{variant}-{victim_spec.replace(':', '-').replace('/', '_')}-{target}-{seed}"
    report = train_baseline_attack(method, victim_spec, target, out, epsilon, norm, seed,
                                   ppo_preset(preset, steps, actor_steps=actor_steps), labels_path)
    lo, hi = report["attack_success_ci"]
    click.echo(f"{method} ({report['variant']}) attack success: {100 * report['attack_success_rate']:.1f}% "
               f"(95% CI {100 * lo:.1f}-{100 * hi:.1f}%, {report['episodes']} episodes); max perturbation "
               f"{report['max_perturbation']:.4f} <= epsilon {epsilon:g} ({norm}); report: {out / 'report.json'}")


@attack.command("eval")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--episodes", type=int, default=30, show_default=True, help="the paper uses 30")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--video", type=click.Path(path_type=Path), default=None, help="record the first two attacked episodes")
@click.option("--json", "as_json", is_flag=True)
def attack_eval(run, episodes, seed, video, as_json) -> None:
    """Evaluate the attack of RUN (RAT or a baseline) against its victim, beside the victim's clean behaviour."""
    from rat.attacks.presets import evaluate_saved_attack

    if episodes <= 0:
        raise RatError(f"--episodes must be positive, got {episodes}")
    r = evaluate_saved_attack(run, episodes, seed, video)
    attacked, clean = r["attack"], r["clean"]
    if as_json:
        click.echo(json.dumps({k: v for k, v in r.items() if k not in ("attack", "clean")} | {
            "attack_success_rate": attacked.result.success_rate, "attack_success_ci": attacked.result.success_ci,
            "clean_target_success_rate": clean.success_rate, "max_perturbation": attacked.max_perturbation,
            "mean_perturbation": attacked.mean_perturbation, "within_budget": attacked.within_budget}))
        return
    click.echo(f"{r['method']} against {r['victim']} on {r['task']}, target '{r['target']}'")
    click.echo(f"  attacked: {attacked.summary()}")
    click.echo(f"  clean:    {clean.summary()}")


@cli.group()
def bench() -> None:
    """Grids of experiments: the paper's tables."""


def _csv(kind):
    return lambda ctx, param, value: [kind(v) for v in value.split(",") if v.strip()] if value else []


@bench.command("table1")
@click.option("--tasks", default="drawer-open-v3,faucet-close-v3", show_default=True, callback=_csv(str),
              help="victim tasks, comma-separated (zoo victims)")
@click.option("--scenarios", default="manipulation,opposite", show_default=True, callback=_csv(str))
@click.option("--methods", default="pa-ad-oracle,pa-ad,sa-rl-oracle,sa-rl,random,rat", show_default=True,
              callback=_csv(str), help="the paper's columns")
@click.option("--seeds", default="0,1,2", show_default=True, callback=_csv(int))
@click.option("--preset", type=click.Choice(["cpu", "paper", "smoke"]), default="cpu", show_default=True,
              help="budgets: cpu 5e4 steps per learner (this machine), paper 1e6 (a GPU cluster), smoke (minutes)")
@click.option("--jobs", type=int, default=2, show_default=True, help="parallel local processes")
@click.option("--ray-address", default=None, help="run the cells as Ray tasks on this cluster ('auto', 'ray://host:10001')")
@click.option("--out", type=click.Path(path_type=Path), default=Path("runs/table1"), show_default=True)
def bench_table1(tasks, scenarios, methods, seeds, preset, jobs, ray_address, out) -> None:
    """Run the grid task × scenario × method × seed (finished cells are skipped) and write table 1."""
    from rat.table1 import GRID_PRESETS, grid_cells, run_grid

    cells = grid_cells(tasks, scenarios, methods, seeds)
    click.echo(f"{len(cells)} cells, preset '{preset}', {'Ray at ' + ray_address if ray_address else f'{jobs} processes'}")
    result = run_grid(cells, GRID_PRESETS[preset], out, jobs, ray_address, echo=click.echo)
    click.echo(f"ran {len(result['ran'])}, skipped {len(result['skipped'])} finished, failed {len(result['failed'])}; "
               f"{out / 'table1.md'}, {out / 'results.csv'}")
    for row in result["failed"]:
        click.echo(f"  failed: {row['task']}/{row['scenario']}/{row['method']}/seed{row['seed']}: {row['error']}", err=True)
    if result["failed"]:
        raise RatError(f"{len(result['failed'])} cells failed (tracebacks in their error.txt); fix and re-run to resume")


# --- entry point -----------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit code (0 ok, 2 user error) instead of exiting."""
    try:
        cli.main(args=argv, prog_name="rat", standalone_mode=False)
    except RatError as exc:
        click.echo(f"rat: error: {exc}", err=True)
        return RatError.exit_code
    except click.exceptions.Abort:
        click.echo("rat: aborted", err=True)
        return 130
    except click.ClickException as exc:
        exc.show()
        return exc.exit_code
    return 0


def entry() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entry()
