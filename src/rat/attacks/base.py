"""One shape for every attack: the :class:`Attack` protocol, its registry, and what it is trained against.

An attack is registered under a name, like a target behaviour::

    from rat.attacks import AttackSetup, register_attack

    @register_attack("zero", rewards=("none",))
    class ZeroAttack:  # never perturbs: a sanity check
        def train(self, setup: AttackSetup, config, out):
            ...  # set up, evaluate with rat.attacks.evaluate_attack, save, return an AttackReport

        def load(self, run, meta, victim):
            return lambda obs: np.zeros_like(obs)

Once registered (in the user's own module, made known to the command line by ``--plugin`` or
the ``rat.plugins`` entry-point group), ``rat attack train --method zero``, ``rat attack eval``,
``rat list attacks`` and the table-1 grid know it.

Where the attack learns from is a property of one method, not a second name: ``reward`` is
``labels`` (preference labels: RAT asks its labeller; the RL baselines read a label store, or a RAT run's own r̂),
``oracle`` (the true target reward) or ``none`` (it learns nothing).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import gymnasium as gym

from rat.attacks.threat import Perturbation, ThreatModel
from rat.checkpoint import read_meta
from rat.envs.targets import TargetBehaviour
from rat.errors import RatError
from rat.plugins import Registry
from rat.preferences.labeller import Labeller
from rat.victims.base import Victim

REWARDS = ("labels", "oracle", "none")


@dataclass(frozen=True)
class AttackSetup:
    """What an attack is trained against, and how.

    Attributes:
        victim: the frozen victim.
        target: the behaviour the attacker wants.
        make_env: ``seed -> environment`` of the target behaviour (its true state is never perturbed).
        threat: the budget.
        seed: seeds everything of the attack: networks, its own draws, training episodes.
        reward: ``labels``, ``oracle`` or ``none`` (see the module docstring).
        labels: a label store to learn r̂ from, or a finished RAT run whose r̂ to use (attacks that learn from
            labels offline).
        labeller: who answers preference queries, for attacks that ask (default: a scripted teacher).
        describe: JSON-able facts recorded in the run and its report (victim spec, victim task, task).
        progress: show progress bars.
        tensorboard: also log to TensorBoard.
    """

    victim: Victim
    target: TargetBehaviour
    make_env: Callable[[int], gym.Env]
    threat: ThreatModel
    seed: int = 0
    reward: str = "labels"
    labels: Path | None = None
    labeller: Labeller | None = None
    describe: dict[str, Any] = field(default_factory=dict)
    progress: bool = True
    tensorboard: bool = False

    def __post_init__(self):
        if self.threat.epsilon == 0:
            raise RatError("epsilon 0 allows no perturbation, so there is nothing to attack with; give --epsilon > 0 "
                           "(rat victim eval measures the clean victim)")
        if self.reward not in REWARDS:
            raise RatError(f"unknown reward source '{self.reward}'; use one of: {', '.join(REWARDS)}")


@runtime_checkable
class Attack(Protocol):
    """A targeted attack: trains in a run directory and loads back as a :data:`Perturbation`.

    Registered attacks also carry ``name``, ``description``, ``config`` (their configuration
    dataclass, or None) and ``rewards`` (the reward sources they support, the default first),
    set by :func:`register_attack`.
    """

    name: str
    description: str
    config: type | None
    rewards: tuple[str, ...]

    def train(self, setup: AttackSetup, config: Any, out: Path):
        """Train (or set up) the attack in run directory ``out``, evaluate it, write ``out/report.json``
        and return the :class:`~rat.reports.AttackReport`."""

    def load(self, run: Path, meta: dict[str, Any], victim: Victim) -> Perturbation:
        """The attack saved in run directory ``run`` (``meta``: its ``adversary.json`` metadata) as ``obs -> Δ``."""


def _load_builtin() -> None:
    """Import the modules whose attacks register themselves."""
    import rat.attacks.probe  # noqa: F401
    import rat.attacks.rat  # noqa: F401
    import rat.attacks.rl  # noqa: F401
    import rat.attacks.simple  # noqa: F401


_REGISTRY: Registry[Attack] = Registry("attack", "rat list attacks", _load_builtin)


def register_attack(name: str, *, config: type | None = None, rewards: tuple[str, ...] = ("none",),
                    description: str = "", overwrite: bool = False) -> Callable[[type], type]:
    """Class decorator: register an attack (made with no arguments) under ``name``."""
    unknown = [r for r in rewards if r not in REWARDS]
    if unknown or not rewards:
        raise RatError(f"attack '{name}': rewards must be some of {', '.join(REWARDS)}, got {', '.join(rewards) or 'none'}")

    def decorate(cls: type) -> type:
        attack = cls()
        attack.name, attack.config, attack.rewards = name, config, tuple(rewards)
        attack.description = description or (cls.__doc__ or "").strip().splitlines()[0]
        _REGISTRY.add(name, attack, overwrite)
        return cls

    return decorate


def get_attack(name: str) -> Attack:
    """Look an attack up by name."""
    return _REGISTRY.get(name)


def list_attacks() -> list[Attack]:
    """Every registered attack, sorted by name."""
    return _REGISTRY.all()


#: what SA-RL and PA-AD learn from when measured beside RAT (table 3, audits): the target's true reward,
#: the paper's oracle variants; every other attack learns from its first reward (RAT: labels)
MEASURED_REWARD = {"sa-rl": "oracle", "pa-ad": "oracle"}


def measured_reward(attack: Attack) -> str:
    """The reward ``attack`` learns from when it is measured beside RAT (:data:`MEASURED_REWARD`)."""
    return MEASURED_REWARD.get(attack.name, attack.rewards[0])


def check_reward(attack: Attack, reward: str) -> str:
    """``reward`` if ``attack`` supports it, else a one-line error naming the ones it does."""
    if reward not in attack.rewards:
        raise RatError(f"attack '{attack.name}' learns from {' or '.join(attack.rewards)}, not '{reward}'; "
                       f"pass --reward {attack.rewards[0]}")
    return reward


SNAPSHOT = "adversary-snapshot"  #: checkpoint kind of a RAT run's snapshots, ``<run>/snapshots/adversary-<step>``


def saved_attack_meta(run: str | Path) -> dict[str, Any]:
    """The metadata of the attack saved in a run directory (``<run>/adversary.json``), or of one saved attack in
    it; a RAT snapshot has its run's, with ``snapshot_step`` added."""
    path = Path(run)
    path = path / "adversary" if path.is_dir() else path
    header = read_meta(path)
    meta = header.get("meta")
    if header.get("kind") == SNAPSHOT and isinstance(meta, dict):  # its own metadata and step
        meta = {k: v for k, v in meta.items() if k != "step"} | {"snapshot_step": meta.get("step")}
    budget = meta.get("rat", meta) if isinstance(meta, dict) else {}
    missing = [k for k in ("target",) if not isinstance(meta, dict) or k not in meta]
    missing += [k for k in ("epsilon", "norm") if not isinstance(budget, dict) or k not in budget]
    if missing:
        raise RatError(f"'{path}.json' lacks {', '.join(missing)}: it was written by an unreleased version of rat, "
                       "edited, or not written by rat; train the attack again")
    return meta


def saved_attack_path(run: str | Path) -> Path:
    """A run directory as it is, or one saved attack in it named with or without its ``.json``/``.safetensors``."""
    path = Path(run)
    return path.with_suffix("") if not path.is_dir() and path.suffix in (".json", ".safetensors") else path


def load_attack(run: str | Path, victim: Victim) -> tuple[Perturbation, dict[str, Any]]:
    """Any saved attack as ``obs -> Δ``, with its metadata (runs written before the registry load too).

    ``run`` is a run directory or one saved attack in it, such as a RAT run's ``adversary-last``.
    """
    meta = saved_attack_meta(run)
    method = meta.get("method", "rat")
    attack = get_attack(method)
    path = saved_attack_path(run)
    if path.is_dir():
        return attack.load(path, meta, victim), meta
    if path.name == "adversary":
        return attack.load(path.parent, meta, victim), meta
    if method != "rat":
        raise RatError(f"a {method} run saves one attack, '{path.parent}/adversary'; evaluate the run directory")
    from rat.attacks.saved import load_rat_attack  # RAT keeps more than one (adversary-last)

    return load_rat_attack(path, victim), meta
