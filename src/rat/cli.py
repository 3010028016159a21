"""The ``rat`` command line. Every user mistake ends in one line on stderr and exit code 2."""

from __future__ import annotations

import copy
import dataclasses
import importlib
import json
import sys
from pathlib import Path

import click

from rat.errors import RatError

# --- options from the configuration dataclasses ---------------------------------------------------------


class ConfigOption(click.Option):
    """An option for one field of a configuration dataclass: its default and help come from the field.

    ``config`` names the dataclass as ``module:Class`` (imported only when the option is used, so
    ``rat --help`` stays fast); ``path`` is the field, dotted for nested ones (``pebble.budget``).
    """

    def __init__(self, param_decls, *, config: str, path: str, **kwargs):
        self.config_ref, self.path = config, path
        kwargs.setdefault("default", self.config_default)
        super().__init__(param_decls, show_default=True, **kwargs)

    @property
    def config_class(self) -> type:
        module, name = self.config_ref.split(":")
        return getattr(importlib.import_module(module), name)

    def config_default(self):
        from rat.configs import field_default

        return field_default(self.config_class, self.path)

    def get_help_record(self, ctx):
        from rat.configs import field_doc

        self.help = self.help or field_doc(self.config_class, self.path)
        self.default = self.config_default()  # resolved: help shows the value itself
        self.show_default = self.default is not None
        return super().get_help_record(ctx)


def config_option(config: str, path: str, *param_decls: str, **kwargs):
    """``@config_option("rat.victims.training:VictimConfig", "bc_updates", "--bc-updates", type=int)``."""
    decls = param_decls or ("--" + path.rsplit(".", 1)[-1].replace("_", "-"),)
    return click.option(*decls, cls=ConfigOption, config=config, path=path, **kwargs)


def set_option(what: str, example: str = "pebble.budget=5000"):
    """``--set name=value`` (repeatable): any field of ``what``'s configuration, nested ones by dotted path."""
    return click.option("--set", "assignments", multiple=True, metavar="NAME=VALUE",
                        help=f"any setting of {what}, e.g. --set {example} (repeatable; see its config class)")


def labeller_options(f):
    """``--labeller scripted|web`` and where and how long the labelling page waits for a person
    (defaults: :class:`rat.labelling.WebLabellingConfig`'s)."""
    options = [
        click.option("--labeller", type=click.Choice(["scripted", "web"]), default="scripted", show_default=True,
                     help="who answers the preference queries: the scripted teacher, or a person on the labelling page"),
        click.option("--web-host", default=None,
                     help="--labeller web: address of the page (any but loopback needs the printed token) [127.0.0.1]"),
        click.option("--web-port", type=int, default=None, help="--labeller web: port of the page [8765]"),
        click.option("--web-timeout", type=float, default=None,
                     help="--labeller web: seconds a round waits for answers [until all are answered]"),
        click.option("--web-fallback", is_flag=True,
                     help="--labeller web: after --web-timeout the scripted teacher answers what is left"),
    ]
    for option in reversed(options):
        f = option(f)
    return f


def make_labeller(kind: str, out: Path, teacher, host: str | None, port: int | None, timeout: float | None,
                  fallback: bool):
    """The labeller a run asks (None: the run's own scripted teacher); a web one starts serving and says where."""
    if kind == "scripted":
        if host is not None or port is not None or timeout is not None or fallback:
            raise RatError("--web-host, --web-port, --web-timeout and --web-fallback apply to --labeller web; add it")
        return None
    from rat.labelling import WebLabeller, WebLabellingConfig
    from rat.preferences.teacher import ScriptedTeacher

    if fallback and timeout is None:
        raise RatError("--web-fallback answers after a timeout; give --web-timeout SECONDS too")
    given = {k: v for k, v in {"host": host, "port": port, "timeout_s": timeout}.items() if v is not None}
    labeller = WebLabeller(out / "labels.sqlite", WebLabellingConfig(**given, fallback=fallback), ScriptedTeacher(teacher))
    labeller.serve()
    click.echo(f"label the queries of this run at {labeller.config.url()} (the run waits at each feedback round)")
    return labeller


def config_from_options(ctx: click.Context, config_cls: type, base=None, assignments=()):
    """``base`` (default: ``config_cls()``) with every :class:`ConfigOption` of the command for ``config_cls``
    that the user gave on the command line, then every ``--set``, applied."""
    from click.core import ParameterSource

    from rat.configs import parse_assignment, with_values

    values = {}
    for param in ctx.command.params:
        if isinstance(param, ConfigOption) and param.config_class is config_cls \
                and ctx.get_parameter_source(param.name) is not ParameterSource.DEFAULT:
            values[param.path] = ctx.params[param.name]
    values |= dict(parse_assignment(config_cls, a) for a in assignments)
    return with_values(base if base is not None else config_cls(), values)


def resolve_device(name: str):
    """:func:`rat.device.resolve_device`, imported when needed (it imports torch)."""
    from rat.device import resolve_device as resolve

    return resolve(name)


# --- the command group ------------------------------------------------------------------------------


def _load_plugins(ctx, param, value):
    from rat.plugins import load_plugins

    specs = [s.strip() for v in value for s in v.split(",") if s.strip()]
    load_plugins(specs)
    return tuple(specs)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="rat")
@click.option("--plugin", "plugins", multiple=True, envvar="RAT_PLUGINS", callback=_load_plugins, expose_value=True,
              metavar="MODULE", help="import MODULE (or a .py file) first: its registered attacks and targets become "
              "usable (repeatable; or RAT_PLUGINS=mod1,mod2)")
@click.pass_context
def cli(ctx: click.Context, plugins: tuple[str, ...]) -> None:
    """Targeted behaviour attacks on deep RL agents (RAT), and the victims they attack."""
    ctx.obj = {"plugins": plugins}


# --- listings ------------------------------------------------------------------------------------


@cli.group("list")
def list_group() -> None:
    """List tasks, target behaviours, attacks and zoo victims."""


@list_group.command("tasks")
@click.option("--all", "show_all", is_flag=True, help="every Meta-World v3 task, not only the paper's eight")
def list_tasks(show_all: bool) -> None:
    """Meta-World v3 tasks (the paper's eight, with their opposites and zoo victims)."""
    from rat.envs import LOCOMOTION_TASKS, PAPER_TASKS, all_tasks
    from rat.victims import zoo_victims
    from rat.victims.zoo import zoo_dt_victims

    zoo, dt = zoo_victims(), zoo_dt_victims()
    click.echo(f"{'task':<18} {'opposite':<18} zoo victims (zoo:<task> is the first)")
    for task, opposite in sorted(PAPER_TASKS.items()):
        names = ", ".join(f"zoo:{task}@{m}" for m in zoo.get(task, [])) or "-"
        click.echo(f"{task:<18} {opposite:<18} {names}")
    for task in LOCOMOTION_TASKS:
        click.echo(f"{task:<18} {'-':<18} {'zoo:' + dt[task] + ' (Decision Transformer)' if task in dt else '-'}")
    if show_all:
        click.echo("\nall tasks (Meta-World v3, then Gymnasium MuJoCo locomotion): " + ", ".join(all_tasks()))


@list_group.command("targets")
def list_targets() -> None:
    """Registered target behaviours."""
    from rat.envs import list_targets as targets

    width = max(len(t.name) for t in targets())
    for t in targets():
        click.echo(f"{t.name:<{width}}  {t.description}")


@list_group.command("attacks")
def list_attacks() -> None:
    """Registered attacks: the rewards each can learn from (the first is its default) and its settings class."""
    from rat.attacks import list_attacks as attacks

    for a in attacks():
        settings = f" (settings: {a.config.__module__}.{a.config.__name__})" if a.config else ""
        click.echo(f"{a.name:<8} [{', '.join(a.rewards)}] {a.description}{settings}")


@list_group.command("presets")
@click.option("--json", "as_json", is_flag=True)
def list_presets(as_json: bool) -> None:
    """What each --preset sets: RAT's settings per scenario (beyond the dataclasses' defaults), PPO's, and robust
    training's. RAT's cpu and smoke presets also spread the label budget over equal rounds (pebble.per_round)."""
    from dataclasses import asdict

    from rat.attacks.rl import PPOConfig
    from rat.experiments.presets import PRESETS, SCENARIOS, ppo_preset, preset_values
    from rat.robust.trainer import SMOKE

    ppo_defaults = asdict(PPOConfig())
    table = {preset: {"rat": {s: preset_values(preset, "reach" if s == "manipulation" else "opposite")
                              for s in SCENARIOS},
                      "ppo": {k: v for k, v in asdict(ppo_preset(preset)).items() if v != ppo_defaults[k]}}
             for preset in PRESETS}
    table["smoke"]["robust"], table["cpu"]["robust"] = SMOKE, {}
    if as_json:
        click.echo(json.dumps(table, indent=1))
        return
    for preset, parts in table.items():
        click.echo(f"--preset {preset}")
        for scenario, values in parts["rat"].items():
            click.echo(f"  rat, {scenario}: " + ", ".join(f"{k}={v}" for k, v in values.items()))
        click.echo("  sa-rl, pa-ad (PPO): " + (", ".join(f"{k}={v}" for k, v in parts["ppo"].items()) or "defaults"))
        if "robust" in parts:
            click.echo("  rat robust train: " + (", ".join(f"{k}={v}" for k, v in parts["robust"].items())
                                                 or "the RobustConfig defaults"))


# --- victims ---------------------------------------------------------------------------------------


@cli.group()
def victim() -> None:
    """Train, evaluate and regenerate victims."""


VICTIM = "rat.victims.training:VictimConfig"
_method_help = "bc: behaviour cloning of the scripted expert (minutes); sac-demo: SAC warm-started with " \
               "demonstrations; sac: SAC from scratch, the paper's way (hours)"


@victim.command("train")
@click.option("--task", required=True, help="Meta-World v3 task, e.g. drawer-open-v3")
@config_option(VICTIM, "method", type=click.Choice(["bc", "sac-demo", "sac"]), help=_method_help)
@config_option(VICTIM, "seed", type=int)
@config_option(VICTIM, "demo_episodes", type=int)
@config_option(VICTIM, "bc_updates", type=int)
@config_option(VICTIM, "total_steps", type=int)
@config_option(VICTIM, "eval_episodes", type=int)
@config_option(VICTIM, "device", type=click.Choice(["auto", "cpu", "cuda"]))
@set_option("the victim (rat.victims.training.VictimConfig)", "sac.batch_size=256")
@click.option("--out", type=click.Path(path_type=Path), default=None, help="run directory [runs/victim-<task>-<method>-<seed>]")
@click.option("--tensorboard", is_flag=True, help="also log to TensorBoard (needs the 'tensorboard' extra)")
@click.pass_context
def victim_train(ctx, task, method, seed, out, tensorboard, assignments, **_) -> None:
    """Train a victim. Re-running with the same --out resumes an interrupted run."""
    from rat.envs import LOCOMOTION_TASKS, check_task
    from rat.runs import check_run_dir
    from rat.victims.training import VictimConfig, train_victim

    check_task(task)
    config = config_from_options(ctx, VictimConfig, base=VictimConfig(task=task, method=method), assignments=assignments)
    resolve_device(config.device)  # a missing GPU is said before anything is written
    out = check_run_dir(out or Path("runs") / f"victim-{task}-{method}-{seed}")
    path, result = train_victim(config, out, progress=True, tensorboard=tensorboard)
    click.echo(f"victim: {path}.safetensors")
    click.echo(f"clean evaluation on {task}: {result.summary(with_success=task not in LOCOMOTION_TASKS)}")


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
    from rat.envs import LOCOMOTION_TASKS, get_target, make_task
    from rat.eval import evaluate
    from rat.experiments.runner import load_victim_for
    from rat.runs import check_writable_file
    from rat.victims import check_compatible
    from rat.victims.base import numpy_policy

    if episodes <= 0:
        raise RatError(f"--episodes must be positive, got {episodes}")
    if video is not None:
        check_writable_file(video)
    behaviour = get_target(target)
    v, _, env_task = load_victim_for(victim_spec, behaviour, task)
    env = make_task(env_task, seed=seed, render_mode="rgb_array" if video else None)
    check_compatible(v, env, f"task '{env_task}'")
    result = evaluate(numpy_policy(v), env, episodes, seed=seed, target=behaviour, video=video,
                      video_episodes=video_episodes, progress=True)
    if as_json:
        click.echo(json.dumps({"victim": victim_spec, "task": env_task, "target": target, **result.to_dict()}))
    else:
        own_return_only = target == "task" and env_task in LOCOMOTION_TASKS  # locomotion tasks have no success test
        click.echo(f"{victim_spec} on {env_task}, target '{target}': {result.summary(not own_return_only)}")
        if video:
            click.echo(f"video: {video}")


DT = "rat.victims.dt_training:DTConfig"


@victim.command("dt")
@config_option(DT, "task", type=click.Choice(["HalfCheetah-v5", "Walker2d-v5"]))
@config_option(DT, "expert", help="the expert whose episodes are the data: a victim spec (a SAC victim's run folder)")
@config_option(DT, "data", help="or expert data already collected (expert-data.safetensors of an earlier run)")
@config_option(DT, "data_episodes", "--episodes", type=int)
@config_option(DT, "updates", type=int)
@config_option(DT, "seed", type=int)
@set_option("the Decision Transformer (rat.victims.dt_training.DTConfig)", "batch_size=128")
@click.option("--out", type=click.Path(path_type=Path), default=None, help="run directory [runs/dt-<task>-<seed>]")
@click.pass_context
def victim_dt(ctx, task, seed, out, assignments, **_) -> None:
    """Make a Decision Transformer victim: an expert's episodes, then a Decision Transformer trained on them
    (the hub checkpoints' shape), saved in the hub's layout. Re-running with the same --out resumes."""
    from rat.runs import check_run_dir
    from rat.victims.dt_training import DTConfig, d4rl_score, train_dt

    config = config_from_options(ctx, DTConfig, assignments=assignments)
    out = check_run_dir(out or Path("runs") / f"dt-{task.lower()}-{seed}")
    directory, result = train_dt(config, out, progress=True)
    click.echo(f"victim: {directory} (load it as {directory}, or copy it into a zoo as dt/{task.lower()})")
    click.echo(f"clean evaluation on {task}: return {result.mean_return:.1f} +- {result.std_return:.1f} over "
               f"{result.episodes} episodes (D4RL score {d4rl_score(task, result.mean_return):.1f})")


@victim.command("zoo")
@click.option("--task", "tasks", multiple=True, help="only these tasks (repeatable) [the paper's eight]")
@click.option("--jobs", type=int, default=2, show_default=True, help="parallel processes")
@click.option("--dest", type=click.Path(path_type=Path), default=None,
              help="zoo folder [your zoo: $RAT_ZOO or ~/.local/share/rat/zoo, searched before the shipped one]")
@click.option("--work-dir", type=click.Path(path_type=Path), default=Path("runs/zoo"), show_default=True)
@config_option(VICTIM, "demo_episodes", type=int)
@config_option(VICTIM, "bc_updates", type=int)
@config_option(VICTIM, "eval_episodes", type=int)
@click.pass_context
def victim_zoo(ctx, tasks, jobs, dest, work_dir, **_) -> None:
    """Regenerate the victim zoo (behaviour cloning, default settings) and record the timings."""
    from rat.envs import check_task
    from rat.runs import check_writable_dir
    from rat.victims.training import VictimConfig
    from rat.victims.zoo import regenerate_zoo, user_zoo_dir

    for t in tasks:
        check_task(t)
    if jobs <= 0:
        raise RatError(f"--jobs must be positive, got {jobs}")

    def report(row):
        click.echo(f"{row['task']:<18} {row['minutes']:5.1f} min  clean success {row['clean_success']:.0%} "
                   f"over {row['episodes']} episodes")

    config = config_from_options(ctx, VictimConfig, base=VictimConfig(method="bc"))
    dest = check_writable_dir(dest or user_zoo_dir(), "--dest")
    check_writable_dir(work_dir, "--work-dir")
    click.echo(f"victims go to {dest}")
    regenerate_zoo(config, list(tasks) or None, work_dir, dest, jobs, on_done=report)


@victim.command("ship")
@click.argument("source", type=click.Path(exists=True, path_type=Path))
@click.argument("name")
@click.option("--dest", type=click.Path(path_type=Path), default=None,
              help="zoo folder [your zoo: $RAT_ZOO or ~/.local/share/rat/zoo, searched before the shipped one]")
@click.option("--episodes", type=int, default=50, show_default=True, help="clean evaluation episodes")
@click.option("--seed", type=int, default=0, show_default=True, help="seed of the clean evaluation's episodes")
@click.option("--note", default=None, help="how it was made, for timings.json")
def victim_ship(source, name, dest, episodes, seed, note) -> None:
    """Put a trained victim (SOURCE: a run directory or a victim checkpoint) into a zoo as zoo:NAME (<task>@<kind>),
    after a clean evaluation that must reach 95% success."""
    from rat.runs import check_writable_dir
    from rat.victims.zoo import ship_victim, user_zoo_dir

    if episodes <= 0:
        raise RatError(f"--episodes must be positive, got {episodes}")
    dest = check_writable_dir(dest or user_zoo_dir(), "--dest")
    row = ship_victim(source, name, dest, episodes, seed=seed, note=note)
    click.echo(f"zoo:{name} in {dest}: clean success {row['clean_success']:.0%} over {row['episodes']} episodes, "
               f"return {row['mean_return']:.0f}")


# --- intention policies and labels -------------------------------------------------------------


@cli.group()
def intention() -> None:
    """Learn a target behaviour from preference labels (PEBBLE), without a victim."""


INTENTION = "rat.preferences.intention:IntentionConfig"


@intention.command("train")
@config_option(INTENTION, "task")
@config_option(INTENTION, "target", help="target behaviour: reach, opposite, or a registered one")
@config_option(INTENTION, "pebble.budget", type=int)
@config_option(INTENTION, "total_steps", "--steps", type=int)
@config_option(INTENTION, "pebble.per_round", type=int)
@config_option(INTENTION, "pebble.feedback_every", "--every", type=int)
@config_option(INTENTION, "pebble.strategy", help="query strategy of later rounds: uniform, disagreement, entropy, "
               "kcenter, kcenter-disagreement, kcenter-entropy")
@config_option(INTENTION, "pebble.seed_steps", type=int)
@config_option(INTENTION, "pebble.unsupervised_steps", "--pretrain-steps", type=int,
               help="state-entropy pre-training steps; the first query round follows")
@config_option(INTENTION, "pebble.sac.batch_size", type=int, help="SAC batch size")
@config_option(INTENTION, "pebble.reward.max_epochs", "--reward-epochs", type=int)
@config_option(INTENTION, "eval_every", type=int)
@config_option(INTENTION, "pebble.oracle", is_flag=True)
@config_option(INTENTION, "pebble.teacher.mistake", "--teacher-mistake", type=float)
@config_option(INTENTION, "pebble.teacher.beta", "--teacher-beta", type=float)
@config_option(INTENTION, "seed", type=int)
@config_option(INTENTION, "device", type=click.Choice(["auto", "cpu", "cuda"]))
@set_option("the run (rat.preferences.intention.IntentionConfig)")
@labeller_options
@click.option("--out", type=click.Path(path_type=Path), default=None, help="run directory [runs/intention-...]")
@click.option("--tensorboard", is_flag=True, help="also log to TensorBoard")
@click.pass_context
def intention_train(ctx, task, target, budget, seed, out, tensorboard, assignments, labeller, web_host, web_port,
                    web_timeout, web_fallback, **_) -> None:
    """Train an intention policy for TARGET from preference labels (scripted, or a person's with --labeller web);
    resumes with the same --out."""
    from rat.preferences.intention import IntentionConfig, train_intention
    from rat.runs import check_run_dir

    config = config_from_options(ctx, IntentionConfig, assignments=assignments)
    resolve_device(config.device)  # a missing GPU is said before anything is written
    out = check_run_dir(out or Path("runs") / f"intention-{task}-{target}-{budget}-{seed}")
    who = make_labeller(labeller, out, config.pebble.teacher, web_host, web_port, web_timeout, web_fallback)
    report = train_intention(config, out, progress=True, tensorboard=tensorboard, labeller=who)
    lo, hi = report.target_success_ci
    click.echo(f"target success of the intention policy: {100 * report.target_success_rate:.1f}% "
               f"(95% CI {100 * lo:.1f}-{100 * hi:.1f}%, {report.final_eval_episodes} episodes)")
    click.echo(f"learned reward: preference accuracy {100 * report.preference_accuracy:.1f}% on "
               f"{report.held_out_pairs} held-out pairs; Pearson r with the true reward {report.reward_pearson:.2f}")
    click.echo(f"labels: {report.labels} of {report.queries_asked} queries asked; run: {out} "
               "(report.json, reward_quality.png, training.png, labels.sqlite)")


@cli.group()
def labels() -> None:
    """List, export, import and serve preference labels (SQLite label stores; `serve`: the labelling page)."""


def _open_store(path: Path):
    """An existing label store, read-only: listing and exporting never write to it."""
    from rat.preferences.store import LabelStore

    return LabelStore(path, read_only=True)


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
            who = row["labeller"].get("type", "?") + (f" {row['labeller']['name']}" if "name" in row["labeller"] else "")
            took = f" in {row['duration_s']:.1f} s" if row.get("duration_s") is not None else ""
            click.echo(f"  #{row['id']:<6} {row['created_at']}  {row['task']}/{row['target']}  round {row['round']}  "
                       f"label {row['label']:.1f}  by {who}{took}")


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
    """Add every label of store file SRC to STORE (created if missing), with its query-round accounting."""
    from rat.preferences.store import LabelStore

    _open_store(src).close()  # SRC is checked before STORE is created
    with LabelStore(store) as s:
        click.echo(f"imported {s.import_from(src, source)} labels into {store}")


@labels.command("serve")
@click.argument("where", type=click.Path(path_type=Path))
@click.option("--host", default=None, help="address (any but loopback needs the token) [127.0.0.1]")
@click.option("--port", type=int, default=None, help="[8765]")
@click.option("--token", default=None, help="access token [generated off loopback]")
def labels_serve(where, host, port, token) -> None:
    """Serve the labelling page for WHERE (a run directory or its labels.sqlite) until interrupted.

    A run with --labeller web serves its own page; this serves a store without one (a run that
    runs elsewhere with --web-host set to not serve, or the page after a restart)."""
    from rat.labelling import WebLabellingConfig
    from rat.labelling.server import serve

    store = where / "labels.sqlite" if where.is_dir() else where
    _open_store(store).close()
    given = {k: v for k, v in {"host": host, "port": port, "token": token}.items() if v is not None}
    config = WebLabellingConfig(**given).with_token()
    click.echo(f"labelling page for {store} at {config.url()} (Ctrl-C stops it; nothing is lost)")
    serve(store, config)


label_alias = copy.copy(labels)  # `rat label serve` reads naturally too
label_alias.hidden = True
cli.add_command(label_alias, "label")


# --- attacks ---------------------------------------------------------------------------------------


@cli.group()
def attack() -> None:
    """Train and evaluate targeted behaviour attacks: RAT and its baselines."""


THREAT = "rat.attacks.threat:ThreatModel"


@attack.command("train")
@click.option("--method", default="rat", show_default=True, help="a registered attack (`rat list attacks`)")
@click.option("--victim", "victim_spec", default="zoo:drawer-open-v3", show_default=True,
              help="zoo:<task>, a Stable-Baselines3 .zip, or a victim checkpoint")
@click.option("--task", default=None, help="the victim's own task, for a victim that does not record one")
@click.option("--target", default="reach", show_default=True,
              help="reach (manipulation scenario), opposite (opposite behaviour), or a registered target")
@click.option("--reward", type=click.Choice(["labels", "oracle", "none"]), default=None,
              help="learn from preference labels, the true target reward (oracle), or nothing [the attack's first]")
@click.option("--labels", "labels_path", type=click.Path(path_type=Path), default=None,
              help="SA-RL, PA-AD with --reward labels: a label store to learn r̂ from (e.g. a RAT run's "
                   "labels.sqlite), or a finished RAT run's directory to attack with the r̂ it ended with")
@config_option(THREAT, "epsilon", type=float, help="budget, raw observation units")
@config_option(THREAT, "norm", type=click.Choice(["linf", "l2", "l1", "l1-rescale"]))
@click.option("--budget", type=int, default=None,
              help="preference labels (queries) in all (RAT) [the preset's: 3000; smoke 40]")
@click.option("--spend-by", type=float, default=None,
              help="RAT (cpu, smoke): spend the label budget by this fraction of the run [0.9]")
@click.option("--seed-steps", type=int, default=None, help="RAT: uniform random steps first [the preset's]")
@click.option("--pretrain-steps", type=int, default=None,
              help="RAT: state-entropy pre-training steps; the first labels and adversary update follow [the preset's]")
@click.option("--preset", type=click.Choice(["cpu", "paper", "smoke"]), default="cpu", show_default=True,
              help="cpu: 5e4 steps, batches of 256 (this machine); paper: 1e6 steps, batch 1024 (a GPU); "
              "smoke: minutes, not results")
@click.option("--steps", type=int, default=None, help="environment steps [the preset's]")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default=None, help="where to train [the attack's]")
@click.option("--seed", type=int, default=0, show_default=True)
@set_option("the attack's configuration (`rat list attacks` names its class)")
@click.option("--out", type=click.Path(path_type=Path), default=None, help="run directory [runs/<method>-...]")
@click.option("--video/--no-video", default=True, show_default=True,
              help="film two of ten attacked episodes, those reaching the target first")
@click.option("--tensorboard", is_flag=True)
@labeller_options
def attack_train(method, victim_spec, task, target, reward, labels_path, epsilon, norm, budget, spend_by, seed_steps,
                 pretrain_steps, preset, steps, device, seed, assignments,
                 out, video, tensorboard, labeller, web_host, web_port, web_timeout, web_fallback) -> None:
    """Train an attack (RAT by default) and evaluate it; re-running with the same --out resumes it."""
    from rat.attacks import ThreatModel, check_reward, get_attack
    from rat.configs import parse_assignment, with_values
    from rat.experiments.runner import attack_config, attack_setup, film_attack, train_attack
    from rat.runs import check_run_dir

    attack = get_attack(method)
    reward = check_reward(attack, reward or attack.rewards[0])
    given = {"device": device}
    fields = set(getattr(attack.config, "__dataclass_fields__", {}))
    overrides = {k: v for k, v in given.items() if v is not None}
    unknown = sorted(k for k in overrides if k not in fields)
    if unknown:
        raise RatError(f"--{unknown[0].replace('_', '-')} does not apply to attack '{method}'; drop it")
    overrides |= {k: v for k, v in {"epsilon": epsilon, "norm": norm, "seed": seed}.items() if k in fields}
    warm_up = {k: v for k, v in {"seed_steps": seed_steps, "unsupervised_steps": pretrain_steps}.items() if v is not None}
    if warm_up:
        if "pebble" not in fields:
            raise RatError(f"--seed-steps and --pretrain-steps do not apply to attack '{method}'; drop them")
        overrides["pebble_overrides"] = warm_up
    if spend_by is not None:
        if "pebble" not in fields:
            raise RatError(f"--spend-by does not apply to attack '{method}'; drop it")
        overrides["spend_by"] = spend_by
    threat = ThreatModel(epsilon, norm)
    setup = attack_setup(victim_spec, target, threat, seed, reward, labels_path, task, tensorboard=tensorboard)
    config = attack_config(method, preset, budget, steps, target, **overrides)
    if assignments:
        if config is None:
            raise RatError(f"attack '{method}' has no settings; drop --set")
        config = with_values(config, dict(parse_assignment(type(config), a) for a in assignments))
    if getattr(config, "device", None) is not None:
        resolve_device(config.device)  # a missing GPU is said before anything is written
    name = victim_spec.replace(":", "-").replace("/", "_")
    out = check_run_dir(out or Path("runs") / f"{method}{'' if reward == attack.rewards[0] else '-' + reward}-{name}-"
                                              f"{target}-{seed}")
    if labeller != "scripted" and "pebble" not in fields:
        raise RatError(f"attack '{method}' asks no preference queries; drop --labeller (it reads labels with --labels)")
    who = make_labeller(labeller, out, getattr(getattr(config, "pebble", None), "teacher", None), web_host, web_port,
                        web_timeout, web_fallback)
    if who is not None:
        setup = dataclasses.replace(setup, labeller=who)
    report = train_attack(method, setup, config, out)
    click.echo(f"{method} ({reward}) {report.summary()}")
    if video:
        filmed = film_attack(out, out / "attack.mp4", seed=seed)
        click.echo(f"video of two of ten attacked episodes, those reaching the target first: {out / 'attack.mp4'} "
                   f"({sum(filmed)}/{len(filmed)} filmed reach the target)")
    if (out / "training.png").exists():
        click.echo(f"plot of success over training: {out / 'training.png'}")
    click.echo(f"report: {out / 'report.json'}")


@attack.command("eval")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--episodes", type=int, default=30, show_default=True, help="the paper uses 30")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--video", type=click.Path(path_type=Path), default=None, help="record the first two attacked episodes")
@click.option("--record", type=click.Path(path_type=Path), default=None,
              help="write every perturbation's size to this CSV (episode, step, norm, epsilon, within_budget)")
@click.option("--refine-steps", type=int, default=None,
              help="RAT only: Adam steps on Δ per observation towards the intention policy's action "
                   "(0: the adversary network's Δ alone) [the run's refine_steps]")
@click.option("--refine-loss", type=click.Choice(["l2", "q", "l2-or-q"]), default=None,
              help="RAT only: what refinement minimises: the squared action gap (l2), the adversary's own "
                   "KL loss (kl), minus the intention policy's critic at the victim's action (q), or l2 and "
                   "then q where l2 leaves a gap above the run's refine_switch_gap (l2-or-q) [the run's refine_loss]")
@click.option("--refine-switch-gap", type=float, default=None,
              help="RAT, refine-loss l2-or-q only: the gap to π_θ's action above which an observation is refined "
                   "by q [the run's refine_switch_gap]")
@click.option("--lockstep", type=int, default=32, show_default=True,
              help="a refined RAT attack: this many episodes side by side, their observations refined together "
                   "(1: one episode at a time, as a video is)")
@click.option("--json", "as_json", is_flag=True)
def attack_eval(run, episodes, seed, video, record, refine_steps, refine_loss, refine_switch_gap, lockstep,
                as_json) -> None:
    """Evaluate the attack of RUN (RAT or a baseline) against its victim, beside the victim's clean behaviour.
    RUN may also name one adversary a RAT run saved: RUN/adversary-last, or RUN/snapshots/adversary-STEP."""
    from rat.experiments.runner import evaluate_saved_attack
    from rat.runs import check_writable_file

    for value, what in ((episodes, "--episodes"), (lockstep, "--lockstep")):
        if value <= 0:
            raise RatError(f"{what} must be positive, got {value}")
    for path, what in ((video, "--video"), (record, "--record")):
        if path is not None:
            check_writable_file(path, what)
    r = evaluate_saved_attack(run, episodes, seed, video, refine_steps=refine_steps, refine_loss=refine_loss,
                              lockstep=lockstep, refine_switch_gap=refine_switch_gap)
    attacked, clean = r["attack"], r["clean"]
    if record is not None:
        attacked.write_records(record)
    if as_json:
        click.echo(json.dumps({k: v for k, v in r.items() if k not in ("attack", "clean")} | {
            "attack_success_rate": attacked.result.success_rate, "attack_success_ci": attacked.result.success_ci,
            "clean_target_success_rate": clean.success_rate, "max_perturbation": attacked.max_perturbation,
            "mean_perturbation": attacked.mean_perturbation, "within_budget": attacked.within_budget,
            "observations": attacked.steps, "record": str(record) if record else None}))
        return
    snapshot = f" (the snapshot at step {r['snapshot_step']})" if r["snapshot_step"] is not None else ""
    click.echo(f"{r['method']}{snapshot} against {r['victim']} on {r['task']}, target '{r['target']}'")
    click.echo(f"  attacked: {attacked.summary()}")
    if r["refined_gap"] is not None:
        click.echo(f"  Δ refined towards π_θ; the gap left to its actions, mean over the observations: {r['refined_gap']:.3f}")
    click.echo(f"  clean:    {clean.summary()}")
    if record is not None:
        click.echo(f"every perturbation's size: {record} ({len(attacked.records)} observations)")


@cli.group()
def robust() -> None:
    """Train agents that resist targeted attacks (RAT-ATLA, RAT-WocaR, ATLA, PA-ATLA) and attack them afresh."""


ROBUST = "rat.robust.trainer:RobustConfig"


@robust.command("train")
@click.option("--method", type=click.Choice(["rat-atla", "rat-wocar", "atla", "pa-atla", "none"]), default="rat-atla",
              show_default=True, help="the defence (docs/robust.md); none: the control")
@click.option("--victim", "victim_spec", default="zoo:faucet-close-v3@sac", show_default=True,
              help="the agent to start from: a SAC victim (zoo:<task>@sac, a victim checkpoint)")
@click.option("--task", default=None, help="the victim's own task, for a victim that does not record one")
@click.option("--target", default="reach", show_default=True,
              help="the behaviour the adversary is trained towards (a target of the victim's own environment)")
@config_option(THREAT, "epsilon", type=float, help="budget, raw observation units")
@config_option(THREAT, "norm", type=click.Choice(["linf", "l2", "l1", "l1-rescale"]))
@config_option(ROBUST, "init", type=click.Choice(["finetune", "scratch"]))
@config_option(ROBUST, "wocar_critic", type=click.Choice(["intention", "worst-case"]))
@config_option(ROBUST, "agent_steps", type=int)
@click.option("--budget", type=int, default=None, help="RAT-ATLA, RAT-WocaR: the adversary's preference labels [3000]")
@click.option("--preset", type=click.Choice(["cpu", "smoke"]), default="cpu", show_default=True,
              help="cpu: the defaults (docs/robust.md); smoke: every phase in minutes, not results")
@click.option("--seed", type=int, default=0, show_default=True)
@set_option("the robust trainer (rat.robust.RobustConfig)", "phase_steps=4000")
@click.option("--adversary-set", "adversary_assignments", multiple=True, metavar="NAME=VALUE",
              help="any setting of the adversary (RATConfig or PPOConfig), e.g. --adversary-set adversary_lr=3e-4")
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="run directory [runs/robust-<method>-<victim>-<target>-<seed>]")
@click.pass_context
def robust_train(ctx, method, victim_spec, task, target, epsilon, norm, init, wocar_critic, agent_steps, budget,
                 preset, seed, assignments, adversary_assignments, out) -> None:
    """Train a robust agent from a victim; re-running with the same --out resumes it."""
    from rat.attacks import ThreatModel
    from rat.envs import get_target
    from rat.robust.run import robust_task, train_robust_from
    from rat.robust.trainer import RobustConfig, robust_preset
    from rat.runs import check_run_dir

    robust_task(victim_spec, get_target(target), task)  # a bad victim or target is said before anything else
    config = config_from_options(ctx, RobustConfig, robust_preset(preset, method=method, seed=seed), assignments)
    resolve_device(config.device)
    name = victim_spec.replace(":", "-").replace("/", "_").replace("@", "-")
    out = check_run_dir(out or Path("runs") / f"robust-{method}-{name}-{target}-{seed}")
    report = train_robust_from(config, victim_spec, target, out, preset, budget, ThreatModel(epsilon, norm), task,
                               adversary_assignments)
    click.echo(f"{method}: clean return {report['clean_return']:.1f} ± {report['clean_return_std']:.1f}, task success "
               f"{100 * report['clean_task_success']:.1f}% over {report['episodes']} episodes "
               f"({report['train_minutes']:.1f} min)")
    if "own_adversary_return" in report:
        click.echo(f"under its own final adversary: return {report['own_adversary_return']:.1f}, the target reached "
                   f"in {100 * report['own_adversary_target_success']:.1f}%")
    click.echo(f"the robust agent, a victim for `rat victim eval` and `rat attack train --victim`: {out}")
    click.echo(f"plot of clean and attacked return over training: {out / 'training.png'}")
    click.echo(f"report: {out / 'report.json'}")


@robust.command("eval")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--attacks", default="rat,pa-ad,sa-rl,random", show_default=True,
              help="comma-separated attacks, each trained afresh against the robust agent")
@click.option("--preset", type=click.Choice(["cpu", "paper", "smoke"]), default="cpu", show_default=True,
              help="the attacks' preset (as `rat attack train --preset`)")
@click.option("--budget", type=int, default=None, help="RAT's preference labels [the preset's]")
@click.option("--episodes", type=int, default=100, show_default=True, help="the paper's table 3 uses 100")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--json", "as_json", is_flag=True)
def robust_eval(run, attacks, preset, budget, episodes, seed, as_json) -> None:
    """Attack the robust agent of RUN afresh with each attack (resumable) and tabulate task return and target success."""
    from rat.attacks import get_attack
    from rat.robust.run import evaluate_robust

    names = [a.strip() for a in attacks.split(",") if a.strip()]
    for name in names:
        get_attack(name)  # an unknown name is said before anything trains
    table = evaluate_robust(run, names, preset, budget, episodes, seed)
    if as_json:
        click.echo(json.dumps(table, indent=1))
        return
    click.echo(f"{table['method']} against {table['target']}: clean return {table['clean_return']:.1f} "
               f"± {table['clean_return_std']:.1f}")
    for name, row in table["attacks"].items():
        click.echo(f"  {name:8s} ({row['reward']}): return {row['return']:.1f} ± {row['return_std']:.1f}, target "
                   f"reached {100 * row['target_success']:.1f}% of {row['episodes']} episodes")
    click.echo(f"table: {Path(run) / 'eval' / 'table.json'}")


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
@click.option("--labels", "labels", default="", callback=_csv(str),
              help="label counts per scenario instead of the preset's (the paper's per row), e.g. "
                   "manipulation=3000,opposite=1000; target=N for locomotion and user targets")
@click.option("--jobs", type=int, default=2, show_default=True, help="parallel local processes")
@click.option("--ray-address", default=None, help="run the cells as Ray tasks on this cluster ('auto', 'ray://host:10001')")
@click.option("--out", type=click.Path(path_type=Path), default=Path("runs/table1"), show_default=True)
@click.option("--report-only", is_flag=True,
              help="run nothing: write the reports of the grid in --out from its finished cells (a grid stopped part-way)")
@click.option("--baseline-reward", type=click.Choice(["offline", "rat"]), default="offline", show_default=True,
              help="preference-based SA-RL and PA-AD: r̂ learnt offline from the RAT cell's labels, or the r̂ the RAT "
                   "cell ended with (the same labels, learnt once)")
@click.option("--adopt", multiple=True, type=click.Path(path_type=Path),
              help="a finished `rat attack train` run to take in as the RAT cell it is (same victim, target, seed "
                   "and configuration), instead of training that cell; repeatable")
@click.pass_context
def bench_table1(ctx, tasks, scenarios, methods, seeds, preset, labels, jobs, ray_address, out, report_only,
                 baseline_reward, adopt) -> None:
    """Run the grid task × scenario × method × seed (finished cells are skipped) and write table 1."""
    from rat.experiments.presets import GRID_PRESETS
    from rat.experiments.table1 import grid_cells, grid_reports, read_grid, run_grid

    if report_only and adopt:
        raise RatError("--report-only runs nothing, so it cannot take in --adopt runs (their cells are evaluated); "
                       "give one or the other")
    if report_only:
        rows = grid_reports(out)
        total = len(read_grid(out)["cells"])
        click.echo(f"{len(rows)} of the grid's {total} cells finished; {out / 'table1.md'}, {out / 'results.csv'}")
        return
    counts = {}
    for item in labels:
        name, _, count = item.partition("=")
        if not count.strip().lstrip("-").isdigit():
            raise RatError(f"--labels '{item}' is not SCENARIO=N; e.g. --labels manipulation=3000,opposite=1000")
        counts[name.strip()] = int(count)
    grid = GRID_PRESETS[preset].with_labels(counts) if counts else GRID_PRESETS[preset]
    grid = dataclasses.replace(grid, baseline_reward=baseline_reward)
    cells = grid_cells(tasks, scenarios, methods, seeds)
    click.echo(f"{len(cells)} cells, preset '{preset}', {'Ray at ' + ray_address if ray_address else f'{jobs} processes'}")
    result = run_grid(cells, grid, out, jobs, ray_address, echo=click.echo, plugins=ctx.obj["plugins"], adopt=adopt)
    click.echo(f"ran {len(result['ran'])}, skipped {len(result['skipped'])} finished, failed {len(result['failed'])}; "
               f"{out / 'table1.md'}, {out / 'results.csv'}")
    for row in result["failed"]:
        click.echo(f"  failed: {row['task']}/{row['scenario']}/{row['method']}/seed{row['seed']}: {row['error']}", err=True)
    if result["failed"]:
        raise RatError(f"{len(result['failed'])} cells failed (tracebacks in their error.txt); fix and re-run to resume")


@bench.command("report")
@click.argument("folder", type=click.Path(path_type=Path))
def bench_report(folder) -> None:
    """Regenerate a folder's table from its recorded results alone: table1.md from results.csv (a table-1 grid, or
    several merged), table3.md from the rows of a table-3 grid."""
    from rat.experiments.table1 import report_grid
    from rat.experiments.table3 import finished_rows, write_table3

    if finished_rows(folder):
        write_table3(folder)
        click.echo(f"{folder / 'table3.md'}")
        return
    click.echo(f"{report_grid(folder)}")


@bench.command("table3")
@click.option("--tasks", default="faucet-close-v3", show_default=True, callback=_csv(str),
              help="tasks with a zoo SAC victim (zoo:<task>@sac or @sac-ft), comma-separated; the paper's: "
                   "door-lock-v3, door-unlock-v3, faucet-open-v3, faucet-close-v3")
@click.option("--rows", default="undefended,none,rat-atla,rat-wocar,rat-wocar-worst,atla,pa-atla", show_default=True,
              callback=_csv(str), help="the defences (each a robust agent trained from the zoo victim; rat-wocar-worst: "
                                       "RAT-WocaR with the worst-case estimate), and the victim itself")
@click.option("--attacks", default="rat,pa-ad,sa-rl,random", show_default=True, callback=_csv(str),
              help="each trained afresh against every row's agent")
@click.option("--seeds", default="0", show_default=True, callback=_csv(int))
@click.option("--target", default="reach", show_default=True, help="the behaviour of RAT's attacks and adversaries")
@click.option("--preset", type=click.Choice(["cpu", "smoke"]), default="cpu", show_default=True,
              help="the robust agents' and the attacks' preset")
@click.option("--episodes", type=int, default=100, show_default=True, help="attacked episodes per cell (the paper's 100)")
@click.option("--jobs", type=int, default=2, show_default=True, help="parallel local processes")
@click.option("--ray-address", default=None, help="run the cells as Ray tasks on this cluster ('auto', 'ray://host:10001')")
@click.option("--out", type=click.Path(path_type=Path), default=Path("runs/table3"), show_default=True)
@click.option("--report-only", is_flag=True, help="run nothing: write table3.md from the finished rows in --out")
def bench_table3(tasks, rows, attacks, seeds, target, preset, episodes, jobs, ray_address, out, report_only) -> None:
    """Train each row's robust agent, attack it with each attack, and write table 3 (finished parts are skipped)."""
    from rat.experiments.table3 import run_table3, write_table3

    done = write_table3(out) if report_only else run_table3(tasks, rows, attacks, seeds, out, preset, target,
                                                              episodes=episodes, echo=click.echo, jobs=jobs,
                                                              ray_address=ray_address)
    click.echo(f"{len(done)} finished rows; {out / 'table3.md'}, {out / 'results.json'}")


@cli.command("audit")
@click.argument("agent")
@click.option("--task", default=None, help="the agent's own task, for an agent that does not record one")
@click.option("--targets", default="reach", show_default=True, callback=_csv(str), help="target behaviours, comma-separated")
@click.option("--epsilons", default="0.02,0.05,0.1", show_default=True, callback=_csv(float),
              help="budgets ε (raw observation units), comma-separated")
@click.option("--norm", type=click.Choice(["linf", "l2", "l1"]), default="linf", show_default=True)
@click.option("--attacks", default="random,mad,probe,sa-rl,rat", show_default=True, callback=_csv(str),
              help="cheapest first; each runs at every target and ε before the next")
@click.option("--budget-minutes", type=float, default=240, show_default=True,
              help="checked before each attack; an attack started is finished")
@click.option("--preset", type=click.Choice(["cpu", "paper", "smoke"]), default="cpu", show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--video/--no-video", default=True, show_default=True,
              help="film the strongest attack of each target at its largest ε")
@click.option("--out", type=click.Path(path_type=Path), default=None, help="the audit's folder [runs/audit-<agent>]")
def audit(agent, task, targets, epsilons, norm, attacks, budget_minutes, preset, seed, video, out) -> None:
    """How robust is AGENT (a zoo victim, an SB3 file, a victim folder)? Every attack at every target and ε, within
    a time budget, resumable; one page: OUT/report.html."""
    from rat.attacks import ThreatModel
    from rat.envs import get_target, make_task
    from rat.experiments.audit import check_audit, run_audit
    from rat.experiments.runner import attack_config, attack_setup, film_attack, load_victim_for
    from rat.pages import write_page
    from rat.victims import check_compatible

    check_audit(epsilons, budget_minutes, attacks)
    for target in targets:  # the agent, its task, each target: checked before anything is written
        victim, _, env_task = load_victim_for(agent, get_target(target), task)
        check_compatible(victim, make_task(env_task), f"task '{env_task}'")
    name = agent.replace(":", "-").replace("/", "_").replace("@", "-")
    out = out or Path("runs") / f"audit-{name}"

    def setup_for(target, epsilon, reward):
        return attack_setup(agent, target, ThreatModel(epsilon, norm), seed, reward, task=task)

    def config_for(method, target):
        return attack_config(method, preset, None, None, target)

    record = run_audit(setup_for, config_for, targets, epsilons, out, budget_minutes, attacks, echo=click.echo,
                       film=(lambda run, path: film_attack(run, path, seed)) if video else None, victim=agent)
    done = sum(r["status"] == "done" for r in record["rows"])
    click.echo(f"{done} of {len(record['rows'])} cells measured in {record['minutes']:.1f} min; "
               f"{write_page(out)}")


@cli.command("report")
@click.argument("folder", type=click.Path(path_type=Path))
def report(folder) -> None:
    """One static HTML page of a run (an attack, a robust agent) or a grid (rat bench table1/table3): FOLDER/report.html."""
    from rat.pages import write_page

    click.echo(f"{write_page(folder)}")


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
    except click.exceptions.NoArgsIsHelpError as exc:  # a bare group: its help, as click would show it
        exc.show()
        return exc.exit_code
    except click.UsageError as exc:  # a wrong option or argument: one line, with where to look
        where = f"; see '{exc.ctx.command_path} --help'" if exc.ctx is not None else ""
        click.echo(f"rat: error: {exc.format_message().rstrip('.')}{where}", err=True)
        return exc.exit_code
    except click.ClickException as exc:
        exc.show()
        return exc.exit_code
    return 0


def entry() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entry()
