"""The victim zoo: one competent victim per paper task, shipped with the package.

Each is ``zoo/<task>.safetensors`` + ``zoo/<task>.json``, made by ``rat victim zoo`` (behaviour
cloning of the scripted expert with DART noise: minutes per task on a CPU, against hours of SAC;
see the README). ``zoo/timings.json`` records what each took to make.

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


def zoo_tasks(directory: Path | None = None) -> list[str]:
    """Tasks with a zoo victim (in ``directory``, or in any zoo)."""
    directories = [directory] if directory is not None else zoo_dirs()
    return sorted({p.stem for d in directories for p in Path(d).glob("*-v3.json")})


def zoo_path(task: str, directory: Path | None = None) -> Path:
    """The checkpoint of ``task``'s zoo victim: the first zoo that has one."""
    for d in [directory] if directory is not None else zoo_dirs():
        path = Path(d) / task
        if path.with_suffix(".json").exists():
            return path
    raise RatError(f"no zoo victim for '{task}'; zoo victims: {', '.join(zoo_tasks(directory)) or 'none'} "
                   "(regenerate with `rat victim zoo`)")


def load_zoo_victim(task: str) -> ModuleVictim:
    """The shipped victim of ``task`` (frozen)."""
    return load_rat_victim(zoo_path(task), name=f"{ZOO_PREFIX}{task}")


def _make_one(args: tuple) -> dict:
    import torch

    from rat.victims.training import train_victim

    torch.set_num_threads(1)
    config, work_dir, dest = args
    started = time.perf_counter()
    path, result = train_victim(config, Path(work_dir) / config.task, progress=False)
    minutes = (time.perf_counter() - started) / 60
    for suffix in (".safetensors", ".json"):
        shutil.copy(path.with_suffix(suffix), Path(dest) / f"{config.task}{suffix}")
    return {"task": config.task, "method": config.method, "minutes": round(minutes, 2),
            "clean_success": result.success_rate, "episodes": result.episodes,
            "success_ci": [round(x, 3) for x in result.success_ci], "mean_return": round(result.mean_return, 1),
            "success_at_last_step": result.success_at_last_step}


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
    timings_path = dest / "timings.json"
    old = json.loads(timings_path.read_text()) if timings_path.exists() else {}
    old.update({r["task"]: r for r in rows})
    timings_path.write_text(json.dumps(dict(sorted(old.items())), indent=1))
    weak = [f"{r['task']} ({r['clean_success']:.0%})" for r in rows if r["clean_success"] < min_success]
    if weak:
        raise RatError(f"victims below {min_success:.0%} clean success: {', '.join(weak)}; "
                       "raise --demo-episodes or --bc-updates and regenerate those tasks")
    return rows
