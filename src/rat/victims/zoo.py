"""The victim zoo: one competent victim per paper task, shipped with the package.

Each is ``zoo/<task>.safetensors`` + ``zoo/<task>.json``, made by ``rat victim zoo`` (behaviour
cloning of the scripted expert with DART noise: minutes per task on a CPU, against hours of SAC;
see the README). ``zoo/timings.json`` records what each took to make.

A zoo may hold victims of several kinds per task, named ``<task>@<method>`` (``@sac``: SAC
agents like the paper's; ``@sac-ft``: a behaviour clone fine-tuned by SAC, where SAC from
demonstrations took too long; ``@bc``: behaviour clones, also stored as plain ``<task>``).
``zoo:<task>`` is the SAC victim where one exists, else the behaviour clone;
``zoo:<task>@sac`` and ``zoo:<task>@bc`` name one kind.

Decision Transformer victims (the paper's case II) are folders in the hub's layout,
``zoo/dt/<task>/`` (``config.json``, ``model.safetensors``, ``rat_dt.json``), named
``zoo:dt/halfcheetah-v5`` and ``zoo:dt/walker2d-v5``; ``rat victim dt`` makes them.

``zoo:<task>`` looks first in the user's zoo (``$RAT_ZOO``, else ``$XDG_DATA_HOME/rat/zoo``, else
``~/.local/share/rat/zoo``), where ``rat victim zoo`` writes, then in the shipped one; the package
itself is written only when asked (``--dest``).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

from rat.envs.metaworld import PAPER_TASKS
from rat.errors import RatError
from rat.victims.adapters import load_rat_victim
from rat.victims.base import ModuleVictim

ZOO_DIR = Path(__file__).resolve().parent.parent / "zoo"  #: the shipped zoo
ZOO_PREFIX = "zoo:"


def user_zoo_dir() -> Path:
    """Where ``rat victim zoo`` writes by default, and where ``zoo:<task>`` looks first."""
    if os.environ.get("RAT_ZOO"):
        return Path(os.environ["RAT_ZOO"])
    data = os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share"
    return Path(data) / "rat" / "zoo"


def zoo_dirs() -> list[Path]:
    """The zoos ``zoo:<task>`` searches, in order: the user's, then the shipped one."""
    return [user_zoo_dir(), ZOO_DIR]


def _kinds(directory: Path) -> dict[str, set[str]]:
    """``{task: {methods}}`` of the victims in one zoo folder (plain ``<task>`` files are behaviour clones)."""
    found: dict[str, set[str]] = {}
    for path in Path(directory).glob("*-v3*.json"):
        task, _, method = path.stem.partition("@")
        found.setdefault(task, set()).add(method or "bc")
    return found


def zoo_victims(directory: Path | None = None) -> dict[str, list[str]]:
    """``{task: [methods]}`` of every zoo victim (in ``directory``, or in any zoo): SAC, the clone, then the rest."""
    merged: dict[str, set[str]] = {}
    for d in [directory] if directory is not None else zoo_dirs():
        for task, methods in _kinds(d).items():
            merged.setdefault(task, set()).update(methods)
    return {t: sorted(m, key=lambda x: (x != "sac", x != "sac-ft", x != "bc", x)) for t, m in sorted(merged.items())}


def sac_victim(task: str) -> str:
    """The zoo's SAC agent of ``task``, the one robust training starts from: ``zoo:<task>@sac`` (SAC from
    demonstrations) where there is one, else ``zoo:<task>@sac-ft`` (the clone fine-tuned by SAC)."""
    kinds = zoo_victims().get(task, [])
    for kind in ("sac", "sac-ft"):
        if kind in kinds:
            return f"{ZOO_PREFIX}{task}@{kind}"
    raise RatError(f"no SAC victim of {task} in the zoo (it has {', '.join(kinds) or 'nothing'}); make one with "
                   f"`rat robust train --method none --victim zoo:{task}@bc` and `rat victim ship RUN {task}@sac-ft`")


DT_PREFIX = "dt/"


def zoo_dt_victims(directory: Path | None = None) -> dict[str, str]:
    """``{task: name}`` of the Decision Transformer victims (``{"HalfCheetah-v5": "dt/halfcheetah-v5"}``)."""
    from rat.envs import LOCOMOTION_TASKS

    found = {}
    for d in [directory] if directory is not None else zoo_dirs():
        for task in LOCOMOTION_TASKS:
            if (Path(d) / "dt" / task.lower() / "config.json").is_file():
                found.setdefault(task, DT_PREFIX + task.lower())
    return found


def zoo_tasks(directory: Path | None = None) -> list[str]:
    """Tasks with a zoo victim (in ``directory``, or in any zoo)."""
    return list(zoo_victims(directory))


def zoo_path(name: str, directory: Path | None = None) -> Path:
    """The checkpoint of zoo victim ``<task>`` or ``<task>@<method>``: the first zoo that has one.

    ``<task>`` alone is the SAC victim where any zoo has one, else the behaviour clone.
    """
    task, _, method = name.partition("@")
    wanted = [method] if method else ["sac", "bc"]
    directories = [directory] if directory is not None else zoo_dirs()
    for m in wanted:
        for d in directories:
            for stem in ([f"{task}@{m}", task] if m == "bc" else [f"{task}@{m}"]):
                if (Path(d) / stem).with_suffix(".json").exists():
                    return Path(d) / stem
    known = [f"{t}@{m}" for t, ms in zoo_victims(directory).items() for m in ms]
    raise RatError(f"no zoo victim '{name}'; zoo victims: {', '.join(known) or 'none'} (regenerate with "
                   "`rat victim zoo`)")


def zoo_dt_path(name: str, directory: Path | None = None) -> Path:
    """The folder of zoo Decision Transformer ``dt/<task>``: the first zoo that has one."""
    for d in [directory] if directory is not None else zoo_dirs():
        if (Path(d) / name / "config.json").is_file():
            return Path(d) / name
    known = [ZOO_PREFIX + n for n in zoo_dt_victims(directory).values()]
    raise RatError(f"no zoo Decision Transformer '{name}'; zoo ones: {', '.join(known) or 'none'} (make one with "
                   "`rat victim dt`)")


def load_zoo_victim(name: str) -> ModuleVictim:
    """The zoo victim ``<task>``, ``<task>@<method>`` or ``dt/<task>`` (frozen)."""
    if name.startswith(DT_PREFIX):
        from rat.victims.sequence import load_decision_transformer

        return load_decision_transformer(zoo_dt_path(name), name=f"{ZOO_PREFIX}{name}")
    return load_rat_victim(zoo_path(name), name=f"{ZOO_PREFIX}{name}")


def _make_one(args: tuple) -> dict:
    import torch

    from rat.victims.training import train_victim

    torch.set_num_threads(1)
    config, work_dir, dest = args
    started = time.perf_counter()
    path, result = train_victim(config, Path(work_dir) / config.task, progress=False)
    minutes = (time.perf_counter() - started) / 60
    name = config.task if config.method == "bc" else f"{config.task}@{config.method.split('-')[0]}"
    for suffix in (".safetensors", ".json"):
        shutil.copy(path.with_suffix(suffix), Path(dest) / f"{name}{suffix}")
    return timing_row(config.task, config.method, minutes, result)


def timing_row(task: str, method: str, minutes: float, result) -> dict:
    """A victim's entry in ``timings.json``: what it took to make and its clean evaluation."""
    return {"task": task, "method": method, "minutes": round(minutes, 2), "clean_success": result.success_rate,
            "episodes": result.episodes, "success_ci": [round(x, 3) for x in result.success_ci],
            "mean_return": round(result.mean_return, 1), "success_at_last_step": result.success_at_last_step}


def record_timings(dest: Path, rows: dict[str, dict]) -> None:
    """Add ``rows`` (by zoo name) to ``dest/timings.json``, keeping the others."""
    path = dest / "timings.json"
    old = json.loads(path.read_text()) if path.exists() else {}
    path.write_text(json.dumps(dict(sorted((old | rows).items())), indent=1))


def ship_victim(source: str | Path, name: str, dest: str | Path | None = None, episodes: int = 50,
                seed: int = 0, min_success: float = 0.95, note: str | None = None) -> dict:
    """Put a trained victim (a run directory holding ``victim.{safetensors,json}``, or that file) into a zoo as
    ``zoo:<name>``, after the zoo's clean evaluation (:func:`~rat.victims.training.clean_evaluation`) of
    ``episodes`` episodes; refuses one below ``min_success``. Returns its ``timings.json`` entry."""
    from rat.victims.training import clean_evaluation

    source = Path(source)
    stem = source / "victim" if source.is_dir() else source.with_suffix("")
    if not stem.with_suffix(".json").exists():
        raise RatError(f"no victim at {source}: give a run directory with victim.json or a victim checkpoint")
    task, _, kind = name.partition("@")
    if not kind or "/" in name:
        raise RatError(f"zoo name '{name}' must read <task>@<kind>, e.g. door-lock-v3@sac")
    victim = load_rat_victim(stem.with_suffix(".safetensors"))
    if victim.meta.get("task") != task:
        raise RatError(f"{source} holds a victim of {victim.meta.get('task')}, not of {task}; name it after its task")
    result = clean_evaluation(victim, task, seed, episodes)
    if result.success_rate < min_success:
        raise RatError(f"{source}: clean success {result.success_rate:.0%} over {episodes} episodes is below "
                       f"{min_success:.0%}; train it further before shipping it")
    dest = Path(dest) if dest is not None else user_zoo_dir()
    dest.mkdir(parents=True, exist_ok=True)
    for suffix in (".safetensors", ".json"):
        shutil.copy(stem.with_suffix(suffix), dest / f"{name}{suffix}")
    row = timing_row(task, victim.meta.get("method", "unknown"), victim.meta.get("train_seconds", 0.0) / 60, result)
    row |= {"note": note} if note else {}
    record_timings(dest, {name: row})
    return row


def regenerate_zoo(config, tasks: list[str] | None = None, work_dir: str | Path = "runs/zoo",
                   dest: str | Path | None = None, jobs: int = 2, min_success: float = 0.95, on_done=None) -> list[dict]:
    """Make a victim for each task with ``config`` (its ``task`` field is replaced), in ``jobs`` processes.

    Writes ``dest/<task>.{safetensors,json}`` and ``dest/timings.json``; raises if a victim's
    clean success is below ``min_success``.
    """
    tasks = tasks or sorted(PAPER_TASKS)
    dest = Path(dest) if dest is not None else user_zoo_dir()
    dest.mkdir(parents=True, exist_ok=True)
    jobs_args = [(replace(config, task=t), str(work_dir), str(dest)) for t in tasks]
    rows = []
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        for row in pool.map(_make_one, jobs_args):
            rows.append(row)
            if on_done is not None:
                on_done(row)
    record_timings(dest, {r["task"]: r for r in rows})
    weak = [f"{r['task']} ({r['clean_success']:.0%})" for r in rows if r["clean_success"] < min_success]
    if weak:
        raise RatError(f"victims below {min_success:.0%} clean success: {', '.join(weak)}; "
                       "raise --demo-episodes or --bc-updates and regenerate those tasks")
    return rows
