"""The ``rat`` command line. Every user mistake ends in one line on stderr and exit code 2."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
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
    result = evaluate(v.act_numpy, env, episodes, seed=seed, target=behaviour, video=video,
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
def victim_zoo(tasks, jobs, dest, work_dir) -> None:
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

    regenerate_zoo(VictimConfig(method="bc"), list(tasks) or None, work_dir, dest or ZOO_DIR, jobs, on_done=report)


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
