"""Victims: the frozen policies under attack, whatever made them."""

from __future__ import annotations

from pathlib import Path

from rat.errors import RatError
from rat.victims.adapters import load_rat_victim, load_sb3_victim, save_victim
from rat.victims.base import ModuleVictim, Victim, check_compatible, freeze
from rat.victims.zoo import ZOO_PREFIX, load_zoo_victim, zoo_tasks, zoo_victims


def load_victim(spec: str) -> ModuleVictim:
    """Load a victim from a specification string.

    - ``zoo:<task>``: a zoo victim, e.g. ``zoo:drawer-open-v3`` (the SAC one where one exists, else the
      behaviour clone), or ``zoo:<task>@sac`` / ``zoo:<task>@bc`` for one kind; ``zoo:dt/<task>`` for a
      Decision Transformer (``zoo:dt/halfcheetah-v5``);
    - a folder in the Hugging Face hub's layout holding a Decision Transformer and ``rat_dt.json``;
    - ``sb3:<file>`` or any ``*.zip``: a Stable-Baselines3 SAC/TD3/PPO model file;
    - a path to this project's victim checkpoint (``victim.json``/``.safetensors``, or the run
      directory holding them).
    """
    if spec.startswith(ZOO_PREFIX):
        return load_zoo_victim(spec[len(ZOO_PREFIX):])
    if spec.startswith("sb3:"):
        return load_sb3_victim(spec[4:])
    path = Path(spec)
    if path.suffix == ".zip":
        return load_sb3_victim(path)
    if path.is_dir():
        for folder in (path, path / "victim"):  # a hub-layout folder, or the run of `rat victim dt` holding one
            if any((folder / w).is_file() for w in ("model.safetensors", "pytorch_model.bin")):
                from rat.victims.sequence import load_decision_transformer

                return load_decision_transformer(folder, name=spec)
        path = path / "victim"
    if not path.with_suffix(".json").exists() and not path.exists():
        raise RatError(f"no victim at '{spec}': give zoo:<task>, a Stable-Baselines3 .zip, or a victim checkpoint "
                       f"(zoo tasks: {', '.join(zoo_tasks())})")
    return load_rat_victim(path, name=spec)


__all__ = [
    "ModuleVictim",
    "Victim",
    "check_compatible",
    "freeze",
    "load_rat_victim",
    "load_sb3_victim",
    "load_victim",
    "load_zoo_victim",
    "save_victim",
    "zoo_tasks",
    "zoo_victims",
]
