"""The r̂ the preference-based baselines attack with: learnt offline from a label store, or a RAT run's own.

SA-RL and PA-AD compared with a RAT run read exactly the labels that run asked. Given its
``labels.sqlite`` they train one reward ensemble on all of them (:func:`learn_reward`); given the
finished run's directory they take the ensemble the run ended with, trained on the same labels
(:func:`run_reward`), and learn nothing. Either way the mean r̂ is their reward;
:func:`reward_source` gives it, or the true target reward (the oracle).
"""

from __future__ import annotations

import contextlib
import dataclasses
from pathlib import Path

import numpy as np
import torch

from rat.checkpoint import load_checkpoint, save_checkpoint
from rat.envs.targets import RewardFn, TargetBehaviour
from rat.errors import RatError
from rat.preferences.reward_model import RewardEnsemble, RewardModelConfig
from rat.preferences.store import LabelStore
from rat.runs import read_run_config, to_jsonable


def learn_reward(labels: str | Path, obs_dim: int, act_dim: int, config: RewardModelConfig = RewardModelConfig(),
                 seed: int = 0, source: str | None = None, cache: bool = False) -> tuple[RewardEnsemble, dict]:
    """A reward ensemble trained on every label of a store (or of one ``source``), once, offline.

    With ``cache``, the ensemble is kept beside the store (``<store>-reward-seed<seed>.safetensors``) and
    reused while the labels, seed and configuration are the same: SA-RL and PA-AD compared with one RAT
    run, and a resumed baseline, then learn it once. Training is deterministic, so this changes no number.
    Processes that want the same uncached ensemble at once (two cells of a grid) take turns on a lock
    file beside it: one learns it, the others wait and read it.
    """
    path = Path(labels)
    if not path.exists():
        raise RatError(f"no label store at '{path}'; give the labels.sqlite of a RAT run (or `rat labels export`)")
    with LabelStore(path) as store:
        data = store.read(source)
    if len(data) == 0:
        raise RatError(f"label store '{path}' holds no labels{f' of {source!r}' if source else ''}")
    if data.pairs.obs0.shape[-1] != obs_dim or data.pairs.act0.shape[-1] != act_dim:
        raise RatError(f"labels in '{path}' are for observations {data.pairs.obs0.shape[-1]}-d and actions "
                       f"{data.pairs.act0.shape[-1]}-d, not {obs_dim}-d and {act_dim}-d; use the labels of this task")
    torch.manual_seed(seed)
    ensemble = RewardEnsemble(obs_dim, act_dim, config)
    key = {"label_ids": [int(r["id"]) for r in data.rows], "seed": seed, "config": to_jsonable(config)}
    kept = path.with_name(f"{path.stem}-reward-seed{seed}")
    with _exclusive(kept.with_suffix(".lock")) if cache else contextlib.nullcontext():
        if cache and kept.with_suffix(".json").exists():
            try:
                state, meta = load_checkpoint(kept, "offline-reward")
            except RatError:
                meta = {}  # unreadable: learn it again below and overwrite
            if all(meta.get(k) == v for k, v in key.items()):
                ensemble.load_state_dict(state["ensemble"])
                ensemble.eval()
                return ensemble, {"labels": len(data), "label_ids": key["label_ids"], **meta["metrics"]}
        p = data.pairs
        metrics = ensemble.train_round(p.obs0, p.act0, p.obs1, p.act1, data.y, np.random.default_rng(seed))
        ensemble.eval()
        if cache:
            save_checkpoint(kept, "offline-reward", {"ensemble": ensemble.state_dict()}, {**key, "metrics": metrics})
        return ensemble, {"labels": len(data), "label_ids": key["label_ids"], **metrics}


def run_reward(run: str | Path, obs_dim: int, act_dim: int) -> tuple[RewardEnsemble, dict]:
    """The reward ensemble a finished RAT (or ``rat intention train``) run ended with, and the labels it learnt from.

    Its configuration comes from the run's ``config.json`` and its weights from the run's last checkpoint,
    written when the run ended; a run that has not finished is refused, so no half-trained r̂ is used unawares.
    """
    run = Path(run)
    if not (run / "report.json").exists() or not (run / "checkpoint.json").exists():
        raise RatError(f"'{run}' is not a finished RAT run (no report.json or checkpoint); give one that finished, "
                       "or its labels.sqlite to learn r̂ from")
    config = read_run_config(run)
    pebble = config.get("rat", config).get("pebble")
    if pebble is None or pebble.get("oracle"):
        raise RatError(f"the run in '{run}' learnt no r̂ (it is {'an oracle run' if pebble else 'no RAT run'}); "
                       "give a RAT run that learnt from labels")
    known = {f.name for f in dataclasses.fields(RewardModelConfig)}
    ensemble = RewardEnsemble(obs_dim, act_dim, RewardModelConfig(**{k: v for k, v in pebble["reward"].items() if k in known}))
    state, meta = load_checkpoint(run / "checkpoint", part=("learner", "ensemble"))  # r̂ alone: not the run's buffers
    try:
        ensemble.load_state_dict(state)
    except (KeyError, RuntimeError) as exc:  # a mismatch of shapes: another task's run
        raise RatError(f"the r̂ of '{run}' does not fit observations {obs_dim}-d and actions {act_dim}-d "
                       f"({exc.__class__.__name__}); use a run on this task") from None
    ensemble.eval()
    with LabelStore(run / "labels.sqlite", read_only=True) as store:
        rows = store.read(meta.get("label_source")).rows
    return ensemble, {"labels": len(rows), "label_ids": [int(r["id"]) for r in rows], "reward_from_run": str(run)}


@contextlib.contextmanager
def _exclusive(lock: Path):
    """Hold an exclusive advisory lock on ``lock`` (created if missing); where ``fcntl`` is missing, none."""
    try:
        import fcntl
    except ImportError:  # not POSIX: two processes may both learn the ensemble, as before
        yield
        return
    with open(lock, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def reward_source(target: TargetBehaviour, ensemble: RewardEnsemble | None) -> RewardFn:
    """The target reward (``ensemble`` None: oracle) or the learned r̂(s, a) of a transition."""
    if ensemble is None:
        return target.reward

    def r_hat(obs, action, next_obs, info) -> float:
        return float(ensemble.r_hat(np.asarray(obs, np.float32), np.asarray(action, np.float32)))

    return r_hat
