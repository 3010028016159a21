"""What every grid of experiments shares (table 1's, table 3's): running cells side by side in local processes or
as Ray tasks on a cluster, a failing cell recorded instead of stopping the grid, and a heartbeat while nothing
finishes.

A grid gives :func:`executor` a picklable ``run(cell, *args) -> dict`` and its cells in waves (a wave's cells may
read what an earlier wave's wrote); each finished cell yields its row as it comes. What a cell is, where it writes
and what its table looks like is the grid's own (:mod:`rat.experiments.table1`, :mod:`rat.experiments.table3`).
"""

from __future__ import annotations

import traceback
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from rat.errors import RatError, require

Runner = Callable[..., dict]  #: ``run(cell, *args) -> row``, importable by name (spawned processes, Ray workers)


def guarded(run: Runner, cell: Any, directory: Path, *args) -> dict:
    """``run(cell, *args)``, or a row ``{"error": ...}`` with the traceback in ``directory/error.txt`` if it raises:
    one cell cannot stop a grid."""
    try:
        return run(cell, *args)
    except Exception as exc:  # noqa: BLE001 - recorded with its traceback and reported
        directory.mkdir(parents=True, exist_ok=True)
        (directory / "error.txt").write_text(traceback.format_exc())
        return {"error": f"{exc.__class__.__name__}: {exc}"}


def executor(jobs: int = 2, ray_address: str | None = None, heartbeat: float = 300.0):
    """``execute(run, cells, *args)``: yields each cell's row as it finishes, and None after ``heartbeat`` seconds
    in which none did. ``jobs`` spawned local processes (one: in this process), or one-CPU Ray tasks on the cluster
    at ``ray_address`` (``pip install 'rat[ray]'``)."""
    if ray_address:
        return _ray(ray_address, heartbeat)
    if jobs <= 0:
        raise RatError(f"--jobs must be positive, got {jobs}")
    return _processes(jobs, heartbeat)


def _processes(jobs: int, heartbeat: float):
    def execute(run: Runner, cells: Iterable[Any], *args) -> Iterator[dict | None]:
        cells = list(cells)
        if not cells:
            return
        if jobs == 1:
            for cell in cells:
                yield run(cell, *args)
            return
        with ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn")) as pool:
            pending = {pool.submit(run, cell, *args) for cell in cells}
            while pending:
                done, pending = wait(pending, timeout=heartbeat, return_when=FIRST_COMPLETED)
                yield from (future.result() for future in done) if done else [None]

    return execute


def _ray(address: str, heartbeat: float):
    ray = require("ray", "ray")

    def execute(run: Runner, cells: Iterable[Any], *args) -> Iterator[dict | None]:
        cells = list(cells)
        if not cells:
            return
        if not ray.is_initialized():
            ray.init(address=address, log_to_driver=False)
        remote = ray.remote(num_cpus=1)(run)
        pending = [remote.remote(cell, *args) for cell in cells]
        while pending:
            done, pending = ray.wait(pending, num_returns=1, timeout=heartbeat)
            yield ray.get(done[0]) if done else None

    return execute
