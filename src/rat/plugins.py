"""Plugins: a user's own attacks and target behaviours, known to the command line without editing rat.

A plugin is a Python module that registers things when imported (``@register_attack``,
``@register_target``). Two ways to make one known:

- per command: ``rat --plugin my_attacks ...`` (a module on the import path, or a ``.py`` file);
  several ``--plugin`` options, or ``RAT_PLUGINS=mod1,mod2`` in the environment;
- once, in a package: an entry point in the ``rat.plugins`` group of its ``pyproject.toml``::

      [project.entry-points."rat.plugins"]
      my_attacks = "my_package.attacks"

Installed plugins load the first time a registry is read; ``--plugin`` modules load before the
command runs and again in every process of a grid.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Callable
from importlib.metadata import entry_points
from pathlib import Path
from typing import Generic, TypeVar

from rat.errors import RatError

ENTRY_POINT_GROUP = "rat.plugins"
T = TypeVar("T")

_loaded: set[str] = set()
_installed_loaded = False


def load_plugin(spec: str) -> None:
    """Import plugin ``spec``: a dotted module name or a path to a ``.py`` file (once per process)."""
    if spec in _loaded:
        return
    path = Path(spec)
    try:
        if spec.endswith(".py"):
            if not path.is_file():
                raise RatError(f"plugin file '{spec}' does not exist; give a .py file or a module name")
            name = f"rat_plugin_{path.stem}"
            module_spec = importlib.util.spec_from_file_location(name, path)
            module = importlib.util.module_from_spec(module_spec)
            sys.modules[name] = module
            module_spec.loader.exec_module(module)
        else:
            importlib.import_module(spec)
    except RatError:
        raise
    except ModuleNotFoundError as exc:
        raise RatError(f"plugin '{spec}' cannot be imported ({exc}); put its folder on PYTHONPATH, "
                       "install its package, or give the path of its .py file") from exc
    except Exception as exc:  # noqa: BLE001 - the user's code: name it and what it raised
        raise RatError(f"plugin '{spec}' failed while importing: {exc.__class__.__name__}: {exc}") from exc
    _loaded.add(spec)


def load_plugins(specs: list[str] | tuple[str, ...]) -> None:
    """Import every plugin of ``specs`` (see :func:`load_plugin`)."""
    for spec in specs:
        load_plugin(spec)


def load_installed_plugins() -> None:
    """Import every module of the ``rat.plugins`` entry-point group (once per process)."""
    global _installed_loaded
    if _installed_loaded:
        return
    _installed_loaded = True
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            ep.load()
        except Exception as exc:  # noqa: BLE001 - an installed package's code
            where = f" (package {ep.dist.name})" if getattr(ep, "dist", None) else ""
            raise RatError(f"installed plugin '{ep.name}'{where} failed to load: {exc.__class__.__name__}: {exc}; "
                           "fix or uninstall it") from exc


def loaded_plugins() -> list[str]:
    """The ``--plugin`` specs loaded in this process, in a stable order (handed to grid workers)."""
    return sorted(_loaded)


class Registry(Generic[T]):
    """Named things of one kind (attacks, target behaviours) that built-in modules and plugins add to.

    Reading it first imports the installed plugins (and ``load_first``, for built-ins that
    register themselves on import).
    """

    def __init__(self, kind: str, listing: str, load_first: Callable[[], None] | None = None):
        self.kind, self.listing, self.load_first = kind, listing, load_first
        self.items: dict[str, T] = {}

    def add(self, name: str, item: T, overwrite: bool = False) -> None:
        if name in self.items and not overwrite:
            raise RatError(f"{self.kind} '{name}' is already registered; pick another name or pass overwrite=True")
        self.items[name] = item

    def _load(self) -> None:
        if self.load_first is not None:
            self.load_first()
        load_installed_plugins()

    def get(self, name: str) -> T:
        self._load()
        if name not in self.items:
            raise RatError(f"unknown {self.kind} '{name}': run `{self.listing}` for the names "
                           f"(a plugin's {self.kind} needs `rat --plugin MODULE ...`)")
        return self.items[name]

    def all(self) -> list[T]:
        """Every registered item, sorted by name."""
        self._load()
        return [self.items[k] for k in sorted(self.items)]
