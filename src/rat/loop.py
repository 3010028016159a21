"""One training-loop skeleton for every learner: resume, evaluation and checkpoint cadence, progress, report.

RAT, the intention policy, victim training and the PPO baselines all run through
:class:`TrainingLoop`. What they train is a :class:`Trainer`: an object that owns its whole
state and advances it one unit at a time (an environment step, a gradient step). The loop
decides when to evaluate, when to checkpoint, what to log and what to show, so each learner
says only what is its own.

A learner that cannot be stepped from outside (Stable-Baselines3's ``learn``) calls
:meth:`TrainingLoop.after` from its own callbacks instead of :meth:`TrainingLoop.run`.

Cadence: an evaluation at every multiple of ``eval_every`` steps; a checkpoint at every
multiple of ``checkpoint_every`` steps, or, with ``checkpoint_at_boundary``, at the first
episode end after it (so a resumed run starts a fresh episode exactly as the uninterrupted one
did), and one when the loop ends. Resuming loads the run's checkpoint into the trainer and
drops metric rows logged after it (all of them when there is no checkpoint yet).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from tqdm.auto import tqdm

from rat.checkpoint import load_checkpoint, save_checkpoint
from rat.errors import RatError
from rat.runs import Run, to_jsonable


@runtime_checkable
class Trainer(Protocol):
    """What :class:`TrainingLoop` drives.

    Attributes:
        kind: the checkpoint kind (checked when a run resumes).
        step: units done so far (environment steps, or gradient steps for behaviour cloning).
        finished: ``True`` once the trainer wants to stop before the loop's total (early stopping).
    """

    kind: str
    step: int
    finished: bool

    def advance(self) -> dict[str, float] | None:
        """Do one unit of work; return the metrics to log at this step (an episode's, say), or None.

        Returning metrics also marks a boundary: a safe point for a checkpoint.
        """

    def evaluate(self) -> dict[str, float]:
        """Evaluate now (called on the evaluation cadence); the metrics are logged at this step."""

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue exactly: networks, optimisers, buffers, random states."""

    def load_state_dict(self, state: dict[str, Any], meta: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned (``meta`` is the checkpoint's JSON metadata)."""

    def checkpoint_meta(self) -> dict[str, Any]:
        """JSON-able facts saved beside the state (the step is added by the loop)."""


class TrainingLoop:
    """Runs a :class:`Trainer` in a :class:`~rat.runs.Run` directory.

    Args:
        run: the run directory (config, metrics, checkpoint).
        trainer: what to train.
        total: the step to stop at.
        eval_every: steps between evaluations (None: never).
        checkpoint_every: steps between checkpoints.
        checkpoint_at_boundary: checkpoint only where :meth:`Trainer.advance` returned metrics.
        desc: progress-bar label.
        progress: show a progress bar.
    """

    def __init__(self, run: Run, trainer: Trainer, total: int, *, eval_every: int | None, checkpoint_every: int,
                 checkpoint_at_boundary: bool = False, desc: str = "training", progress: bool = True):
        self.run_dir, self.trainer, self.total = run, trainer, int(total)
        self.eval_every, self.checkpoint_every = eval_every, checkpoint_every
        self.at_boundary, self.desc, self.progress = checkpoint_at_boundary, desc, progress
        self.saved_step = -1
        self.started = time.perf_counter()
        self.seconds_before = 0.0  # training seconds of the sessions before this one, as of the checkpoint resumed
        self.session_seconds = 0.0
        self.bar: tqdm | None = None
        self._schedule(trainer.step)

    def _schedule(self, step: int) -> None:
        self.next_eval = (step // self.eval_every + 1) * self.eval_every if self.eval_every else None
        self.next_checkpoint = (step // self.checkpoint_every + 1) * self.checkpoint_every

    # --- resume and checkpoints ---------------------------------------------------------------

    def resume(self) -> bool:
        """Load the run's checkpoint into the trainer if there is one; returns whether it did."""
        run = self.run_dir
        if not run.has_checkpoint():
            run.logger.truncate_after(-1)  # killed before its first checkpoint: start afresh, rows and all
            return False
        state, meta = load_checkpoint(run.checkpoint_path, self.trainer.kind)
        try:
            self.trainer.load_state_dict(state, meta)
            self.seconds_before = float(meta["seconds"])
        except KeyError as missing:  # a checkpoint of an unreleased layout: say so, change nothing
            raise RatError(f"the checkpoint in '{run.dir}' lacks {missing}: an unreleased version of rat wrote it; "
                           "train into a new --out (or delete its checkpoint.* to start this one afresh)") from None
        run.logger.truncate_after(self.trainer.step)
        self._schedule(self.trainer.step)
        self.saved_step = self.trainer.step
        return True

    def checkpoint(self) -> None:
        meta = {"step": self.trainer.step, "seconds": round(self.total_seconds, 1), **self.trainer.checkpoint_meta()}
        save_checkpoint(self.run_dir.checkpoint_path, self.trainer.kind, self.trainer.state_dict(), meta)
        self.saved_step = self.trainer.step

    # --- the loop ------------------------------------------------------------------------------

    def log(self, step: int, metrics: dict[str, float]) -> None:
        self.run_dir.logger.log(step, metrics)

    def after(self, step: int, metrics: dict[str, float] | None = None, boundary: bool | None = None) -> None:
        """Book-keeping after a unit of work that reached ``step``: log, evaluate and checkpoint when due."""
        if self.bar is None:
            self.open()
        self.bar.update(step - self.bar.n)
        boundary = metrics is not None if boundary is None else boundary
        if metrics is not None:
            self.log(step, metrics)
        if self.next_eval is not None and step >= self.next_eval:
            self.next_eval += self.eval_every
            result = self.trainer.evaluate()
            self.log(step, result)
            self.bar.set_postfix(self._postfix(result))
        if step >= self.next_checkpoint and (boundary or not self.at_boundary):
            self.next_checkpoint += self.checkpoint_every
            self.checkpoint()

    def run(self) -> float:
        """Advance the trainer to ``total`` (or until it is finished); returns this session's seconds."""
        self.open()
        while self.trainer.step < self.total and not self.trainer.finished:
            metrics = self.trainer.advance()
            self.after(self.trainer.step, metrics)
        if self.saved_step != self.trainer.step:
            self.checkpoint()
        return self.close()

    @property
    def total_seconds(self) -> float:
        """Training seconds over every session of the run: those before the checkpoint resumed, and this one's.

        Work done after a session's last checkpoint is lost with it and counted when it is done again.
        """
        running = time.perf_counter() - self.started if self.bar is not None else 0.0
        return self.seconds_before + self.session_seconds + running

    def open(self) -> None:
        if self.bar is None:
            self.started = time.perf_counter()
            self.bar = tqdm(total=self.total, initial=self.trainer.step, desc=self.desc, disable=not self.progress)

    def close(self) -> float:
        """Close the progress bar; returns this session's seconds since :meth:`open`."""
        seconds = 0.0
        if self.bar is not None:
            self.bar.close()
            self.bar = None
            seconds = time.perf_counter() - self.started
            self.session_seconds += seconds
        return seconds

    @staticmethod
    def _postfix(metrics: dict[str, float]) -> dict[str, str]:
        shown = {}
        if "eval_success_rate" in metrics:
            shown["success"] = f"{metrics['eval_success_rate']:.0%}"
        if "labels" in metrics:
            shown["labels"] = f"{int(metrics['labels'])}"
        return shown


def write_report(directory: str | Path, report: Any) -> Path:
    """Write a run's ``report.json`` atomically (a dataclass or a dict)."""
    path = Path(directory) / "report.json"
    tmp = path.with_name("report.json.tmp")
    tmp.write_text(json.dumps(to_jsonable(report), indent=1))
    os.replace(tmp, path)
    return path
