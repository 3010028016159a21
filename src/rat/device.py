"""Where tensors live: ``auto`` (a GPU when torch sees one), ``cpu`` or ``cuda`` (``cuda:N``)."""

from __future__ import annotations

import torch

from rat.errors import RatError

DEVICES = ("auto", "cpu", "cuda")


def resolve_device(name: str = "auto") -> torch.device:
    """The torch device for a configuration's ``device`` setting, or a one-line error naming the fix."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    if name == "cuda" or name.startswith("cuda:"):
        if not torch.cuda.is_available():
            raise RatError(f"device '{name}' asked for, but torch sees no GPU; use --device cpu (or auto)")
        return torch.device(name)
    raise RatError(f"unknown device '{name}'; use one of: auto, cpu, cuda, cuda:N")
