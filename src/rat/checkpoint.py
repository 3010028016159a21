"""Checkpoints as safetensors + JSON: self-describing, and loading never executes code.

A checkpoint ``NAME`` is two files: ``NAME.safetensors`` holds every tensor and array, and
``NAME.json`` holds everything else (what the checkpoint is, its configuration, the nested
structure of optimiser states with tensors replaced by references). Writes are atomic
(temporary file, then rename), so a run killed mid-write keeps its previous checkpoint.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from rat.errors import RatError

FORMAT = "rat-checkpoint"
VERSION = 1


def _flatten(tree: Any, prefix: str, tensors: dict[str, torch.Tensor]) -> Any:
    """Replace every tensor/array leaf of ``tree`` by a reference, collecting it in ``tensors``."""
    if isinstance(tree, torch.Tensor):
        tensors[prefix] = tree.detach().cpu().contiguous()
        return {"__tensor__": prefix}
    if isinstance(tree, np.ndarray):
        tensors[prefix] = torch.from_numpy(np.ascontiguousarray(tree))
        return {"__ndarray__": prefix}
    if isinstance(tree, dict):
        items = [[k, _flatten(v, f"{prefix}/{k}", tensors)] for k, v in tree.items()]
        if all(isinstance(k, str) for k in tree):
            return {"__dict__": {k: v for k, v in items}}
        return {"__items__": items}  # optimiser states key parameters by int
    if isinstance(tree, (list, tuple)):
        return {"__list__": [_flatten(v, f"{prefix}/{i}", tensors) for i, v in enumerate(tree)],
                "tuple": isinstance(tree, tuple)}
    if isinstance(tree, (np.integer, np.floating, np.bool_)):
        return tree.item()
    if tree is None or isinstance(tree, (bool, int, float, str)):
        return tree
    raise TypeError(f"cannot store {type(tree).__name__} in a checkpoint")


def _unflatten(node: Any, tensors: dict[str, torch.Tensor]) -> Any:
    if isinstance(node, dict):
        if "__tensor__" in node:
            return tensors[node["__tensor__"]]
        if "__ndarray__" in node:
            return tensors[node["__ndarray__"]].numpy()
        if "__dict__" in node:
            return {k: _unflatten(v, tensors) for k, v in node["__dict__"].items()}
        if "__items__" in node:
            return {k: _unflatten(v, tensors) for k, v in node["__items__"]}
        if "__list__" in node:
            items = [_unflatten(v, tensors) for v in node["__list__"]]
            return tuple(items) if node.get("tuple") else items
    return node


def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(path.name + ".tmp")
    write(tmp)
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)


def save_checkpoint(path: str | Path, kind: str, state: dict[str, Any], meta: dict[str, Any]) -> Path:
    """Write ``path.safetensors`` and ``path.json``.

    Args:
        path: checkpoint path without suffix (a suffix is stripped).
        kind: what this is (``"victim"``, ``"sac-run"``, ...); checked on load.
        state: nested dicts/lists of tensors, arrays and plain values.
        meta: JSON-able description (configuration, spaces, provenance).
    """
    path = Path(path)
    path = path.with_suffix("") if path.suffix in (".json", ".safetensors") else path
    path.parent.mkdir(parents=True, exist_ok=True)
    tensors: dict[str, torch.Tensor] = {}
    skeleton = _flatten(state, "state", tensors)
    header = {"format": FORMAT, "version": VERSION, "kind": kind, "meta": meta, "state": skeleton}
    _atomic_write(path.with_suffix(".safetensors"), lambda p: save_file(tensors, str(p)))
    # The JSON is written last: its presence marks a complete checkpoint.
    _atomic_write(path.with_suffix(".json"), lambda p: p.write_text(json.dumps(header, indent=1)))
    return path


def read_meta(path: str | Path, kind: str | None = None) -> dict[str, Any]:
    """Read and check a checkpoint's JSON header (no tensors)."""
    path = Path(path)
    path = path.with_suffix("") if path.suffix in (".json", ".safetensors") else path
    json_path = path.with_suffix(".json")
    if not json_path.exists():
        raise RatError(f"no checkpoint at '{path}': expected {json_path.name} and {path.name}.safetensors beside it")
    try:
        header = json.loads(json_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise RatError(f"checkpoint '{json_path}' is corrupted ({exc.__class__.__name__}); restore it or make it again") from exc
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise RatError(f"'{json_path}' is not a rat checkpoint; load foreign models through their adapter "
                       "(see `rat victim eval --help`)")
    if kind is not None and header.get("kind") != kind:
        raise RatError(f"'{json_path}' is a '{header.get('kind')}' checkpoint, not a '{kind}' one")
    return header


def _references(node: Any) -> list[str]:
    """The names of the tensors a checkpoint's skeleton (or a part of it) refers to."""
    if not isinstance(node, dict):
        return []
    if "__tensor__" in node or "__ndarray__" in node:
        return [node.get("__tensor__") or node["__ndarray__"]]
    if "__dict__" in node:
        children = list(node["__dict__"].values())
    elif "__items__" in node:
        children = [v for _, v in node["__items__"]]
    else:
        children = node.get("__list__", [])
    return [name for child in children for name in _references(child)]


def load_checkpoint(path: str | Path, kind: str | None = None, part: tuple[str, ...] = ()
                    ) -> tuple[Any, dict[str, Any]]:
    """Read a checkpoint written by :func:`save_checkpoint`; returns ``(state, meta)``.

    ``part`` names keys to follow from the top of the state (``("learner", "ensemble")``): then only that
    part of the state is returned, and only its tensors are read from the file.
    """
    path = Path(path)
    path = path.with_suffix("") if path.suffix in (".json", ".safetensors") else path
    header = read_meta(path, kind)
    skeleton = header["state"]
    for key in part:
        if not isinstance(skeleton, dict) or key not in skeleton.get("__dict__", {}):
            raise RatError(f"checkpoint '{path}' holds no '{'/'.join(part)}' (no '{key}'); give a checkpoint that "
                           "has one")
        skeleton = skeleton["__dict__"][key]
    try:
        with safe_open(str(path.with_suffix(".safetensors")), framework="pt") as handle:
            stored = set(handle.keys())
            tensors = {name: handle.get_tensor(name) for name in _references(skeleton) if name in stored}
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise RatError(f"checkpoint tensors '{path}.safetensors' are unreadable or corrupted ({exc}); "
                       "restore the file or make the checkpoint again") from exc
    try:
        state = _unflatten(skeleton, tensors)
    except KeyError as exc:
        raise RatError(f"checkpoint '{path}' is corrupted: tensor {exc} is missing from its .safetensors file") from exc
    return state, header["meta"]
