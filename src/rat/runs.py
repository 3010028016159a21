"""Run directories: the resolved configuration, metrics as CSV (TensorBoard when asked), checkpoints.

Layout of a run directory::

    config.json          the resolved configuration (written once; a resume checks it)
    metrics.csv          one row per logged step, columns grow as metrics appear
    checkpoint.json/.safetensors   the latest checkpoint (atomic replace)
    run.lock             held (flock) by the process working in the run; names it
    tensorboard/         only with tensorboard=True

A directory is claimed before anything is written to it: it must be new, empty, or a run of
ours (it holds ``config.json``), and no other process may hold its lock.
"""

from __future__ import annotations

import csv
import fcntl
import functools
import json
import os
import random
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rat.errors import RatError, require


@functools.cache
def git_commit() -> str:
    """The commit of the code that runs, or ``"unknown"`` outside a git checkout: read once, when a process first
    asks (a :class:`Run` asks as it opens), so a long run reports the code it started with, not a later checkout's."""
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5,
                             cwd=Path(__file__).resolve().parent)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def to_jsonable(value: Any) -> Any:
    """Dataclasses, tuples and numpy scalars as plain JSON values."""
    if is_dataclass(value):
        return to_jsonable(asdict(value))
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


class MetricsLogger:
    """Appends metric rows to ``metrics.csv`` and, if asked, to TensorBoard.

    The CSV is rewritten with a wider header when a new metric name appears, so every row
    stays readable by any CSV reader.
    """

    def __init__(self, directory: Path, tensorboard: bool = False):
        self.path = directory / "metrics.csv"
        self.columns: list[str] = []
        if self.path.exists():
            with open(self.path, newline="") as f:
                self.columns = next(csv.reader(f), [])
        self.writer = None
        if tensorboard:
            tb = require("torch.utils.tensorboard", "tensorboard")
            self.writer = tb.SummaryWriter(str(directory / "tensorboard"))

    def log(self, step: int, metrics: dict[str, float]) -> None:
        row = {"step": step, **{k: float(v) for k, v in metrics.items()}}
        new = [k for k in row if k not in self.columns]
        if new:
            old_rows = self.read() if self.path.exists() else []
            self.columns = self.columns + new if self.columns else list(row)
            with open(self.path, "w", newline="") as f:
                w = csv.DictWriter(f, self.columns)
                w.writeheader()
                w.writerows(old_rows)
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, self.columns).writerow(row)
        if self.writer is not None:
            for k, v in metrics.items():
                self.writer.add_scalar(k, v, step)

    def read(self) -> list[dict[str, str]]:
        with open(self.path, newline="") as f:
            return list(csv.DictReader(f))

    def truncate_after(self, step: int) -> None:
        """Drop rows logged after ``step`` (a resumed run redoes them)."""
        if self.path.exists():
            rows = [r for r in self.read() if float(r["step"]) <= step]
            with open(self.path, "w", newline="") as f:
                w = csv.DictWriter(f, self.columns)
                w.writeheader()
                w.writerows(rows)


def _flatten(config: Any, prefix: str = "") -> dict[str, Any]:
    """``{"pebble": {"budget": 3}}`` as ``{"pebble.budget": 3}``."""
    if not isinstance(config, dict):
        return {prefix: config}
    flat: dict[str, Any] = {}
    for key, value in config.items():
        flat |= _flatten(value, f"{prefix}.{key}" if prefix else str(key))
    return flat


#: settings a run may change when it resumes: where it runs, and how often it checkpoints (a checkpoint
#: saves the random streams and reads none, so a run cut into more pieces computes the same numbers)
UNCOUNTED = ("device", "checkpoint_every")


def config_differences(saved: dict[str, Any], now: dict[str, Any], defaults: dict[str, Any] | None = None
                       ) -> list[str]:
    """The settings in which a run directory's configuration and this one differ, as ``name = run vs now``.

    Settings that change nothing a run computes never count (:data:`UNCOUNTED`: a run may resume on another
    machine, or checkpoint more or less often). A setting the run did not record (it was written by an older
    version) counts only if it is set now to other than its default.
    """
    saved, now = _flatten(saved), _flatten(now)
    defaults = _flatten(defaults) if defaults is not None else {}
    differences = []
    for key in sorted(set(saved) | set(now)):
        if key.rsplit(".", 1)[-1] in UNCOUNTED:
            continue
        if key not in saved and key in defaults and now.get(key) == defaults[key]:
            continue
        if saved.get(key, "<not recorded>") != now.get(key, "<not set>"):
            differences.append(f"{key} = {json.dumps(saved.get(key, '<not recorded>'))} in the run, "
                               f"{json.dumps(now.get(key, '<not set>'))} now")
    return differences


def read_run_config(directory: str | Path) -> dict[str, Any]:
    """The configuration a run directory was started with (its ``config.json``); a missing or damaged one is
    refused in one line."""
    path = Path(directory) / "config.json"
    try:
        saved = json.loads(path.read_text())
    except FileNotFoundError:
        raise RatError(f"'{directory}' is not a run directory (no config.json); give the --out of a rat run") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise RatError(f"run configuration '{path}' is corrupted ({exc.__class__.__name__}); restore it from a copy, "
                       "or start the run again in a new --out") from None
    if not isinstance(saved, dict):
        raise RatError(f"run configuration '{path}' is not a JSON object; restore it from a copy, or start the run "
                       "again in a new --out")
    return saved


def differences_from_run(directory: str | Path, config: Any) -> list[str]:
    """:func:`config_differences` between the configuration a run directory was started with and ``config``
    (a dataclass, or a dict holding some), settings added since the run counting only away from their defaults."""
    return config_differences(read_run_config(directory), to_jsonable(config), _defaults(config))


def _defaults(config: Any) -> Any:
    """The default settings of the dataclasses in ``config`` (itself one, or a dict holding some)."""
    if isinstance(config, dict):
        return {k: d for k, v in config.items() if (d := _defaults(v)) is not None}
    try:
        return to_jsonable(type(config)()) if is_dataclass(config) else None
    except Exception:  # noqa: BLE001 - a configuration without defaults for every field
        return None


def check_writable_dir(directory: str | Path, what: str = "--out") -> Path:
    """Create ``directory`` (and its parents) if needed and check that files can be written in it."""
    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        probe = directory / f".rat-write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except FileExistsError as exc:
        raise RatError(f"{what} '{directory}' is a file, not a folder; give a folder") from exc
    except NotADirectoryError as exc:
        raise RatError(f"{what} '{directory}' lies under a file; give a folder path") from exc
    except OSError as exc:
        raise RatError(f"cannot write in {what} '{directory}' ({exc.strerror or exc}); give a writable folder") from exc
    return directory


def check_writable_file(path: str | Path, what: str = "--video") -> Path:
    """Check before any work that ``path`` can be written (its folder is made if missing)."""
    path = Path(path)
    if path.is_dir():
        raise RatError(f"{what} '{path}' is a folder; give a file name")
    check_writable_dir(path.parent if str(path.parent) else Path("."), f"the folder of {what}")
    if path.exists() and not os.access(path, os.W_OK):
        raise RatError(f"cannot overwrite {what} '{path}' (read-only); give another file name")
    return path


def check_run_dir(directory: str | Path, what: str = "--out") -> Path:
    """Check, without creating or writing anything, that ``directory`` can hold a run: it is a new folder
    in a writable place, an empty folder, or a run of ours; otherwise a one-line error."""
    directory = Path(directory)
    if directory.exists():
        if not directory.is_dir():
            raise RatError(f"{what} '{directory}' is a file, not a folder; give a folder")
        if any(p.name != "run.lock" for p in directory.iterdir()) and not (directory / "config.json").exists():
            raise RatError(f"{what} '{directory}' is not empty and is not a rat run (it has no config.json); give a "
                           "new or empty folder")
        existing = directory
    else:
        existing = directory.parent
        while not existing.exists() and existing != existing.parent:
            existing = existing.parent
        if not existing.is_dir():
            raise RatError(f"{what} '{directory}' lies under a file ('{existing}'); give a folder path")
    try:
        with tempfile.TemporaryFile(dir=existing):  # a real write: permissions, read-only file systems, quotas
            pass
    except OSError as exc:
        raise RatError(f"cannot write in {what} '{directory}' ('{existing}': {exc.strerror or exc}); give a "
                       "writable folder") from exc
    return directory


_HELD_LOCKS: dict[Path, int] = {}  # run directory -> the lock file this process holds open


def claim_run_dir(directory: Path) -> None:
    """Lock ``directory`` for this process (released when it exits), or a one-line error naming the holder.

    A process may claim its own run again (a resumed run in the same process).
    """
    key = directory.resolve()
    if key in _HELD_LOCKS:
        return
    fd = os.open(directory / "run.lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 4096).decode(errors="replace").strip() or "another process"
        os.close(fd)
        raise RatError(f"run directory '{directory}' is in use by {holder}; wait for it to finish, or give "
                       "another --out") from None
    os.ftruncate(fd, 0)
    command = " ".join(Path(a).name if i == 0 else a for i, a in enumerate(sys.argv))[:200]
    os.write(fd, f"process {os.getpid()} on {socket.gethostname()} ({command}) since "
                 f"{time.strftime('%Y-%m-%d %H:%M:%S')}\n".encode())
    _HELD_LOCKS[key] = fd


class Run:
    """A run directory. ``Run(dir, config)`` starts it or, if it already holds the same config, resumes it.

    The directory is refused if it is a file, not writable, not empty and not a run of ours, or
    in use by another process (see :func:`claim_run_dir`).
    """

    def __init__(self, directory: str | Path, config: Any, tensorboard: bool = False):
        git_commit()  # the code this process runs, read before the checkout can move on
        self.dir = check_run_dir(directory)  # writable, ours or empty: checked without writing
        self.dir.mkdir(parents=True, exist_ok=True)
        claim_run_dir(self.dir)
        self.config = to_jsonable(config)
        config_path = self.dir / "config.json"
        if config_path.exists():
            differences = differences_from_run(self.dir, config)
            if differences:
                raise RatError(f"run directory '{self.dir}' holds a different configuration (differs in: "
                               f"{'; '.join(differences)}); pick a new --out directory or repeat the original options")
        else:
            config_path.write_text(json.dumps(self.config, indent=1))
        self.logger = MetricsLogger(self.dir, tensorboard)

    @property
    def checkpoint_path(self) -> Path:
        return self.dir / "checkpoint"

    def has_checkpoint(self) -> bool:
        return self.checkpoint_path.with_suffix(".json").exists()


# --- random-generator states -------------------------------------------------------------------


def rng_state(rng: np.random.Generator) -> dict[str, Any]:
    """Everything needed to continue the random streams exactly: ``rng``, numpy, Python, torch."""
    return {
        "generator": json.dumps(rng.bit_generator.state),
        "torch": torch.get_rng_state(),
        "python": json.dumps(random.getstate()),
        "numpy_global": json.dumps(np.random.get_state(legacy=False), default=lambda a: a.tolist()),
    }


def restore_rng_state(rng: np.random.Generator, state: dict[str, Any]) -> None:
    rng.bit_generator.state = json.loads(state["generator"])
    torch.set_rng_state(state["torch"])
    py = json.loads(state["python"])
    random.setstate((py[0], tuple(py[1]), py[2]))
    g = json.loads(state["numpy_global"])
    g["state"]["key"] = np.asarray(g["state"]["key"], np.uint32)
    np.random.set_state(g)


def seed_everything(seed: int) -> np.random.Generator:
    """Seed Python, numpy's global state and torch; return the run's own generator."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    return np.random.default_rng(seed)
