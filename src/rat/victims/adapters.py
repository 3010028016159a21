"""Adapters that turn saved agents into :class:`~rat.victims.base.Victim` objects.

- this project's victim checkpoints (safetensors + JSON);
- Stable-Baselines3 SAC, TD3 (and DDPG) and PPO (and A2C) model files. The zip is read without
  unpickling anything: the spaces come from the readable fields of its ``data`` JSON, the
  weights from ``policy.pth`` loaded with ``weights_only=True``, and the actor is rebuilt from
  the weights' shapes. (``stable_baselines3.*.load`` would unpickle, i.e. run code from the file.)
- any torch module: :class:`~rat.victims.base.ModuleVictim`.
"""

from __future__ import annotations

import base64
import io
import json
import pickle
import pickletools
import zipfile
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from rat.agents.networks import TanhGaussianActor
from rat.checkpoint import load_checkpoint, save_checkpoint
from rat.errors import RatError
from rat.victims.base import ModuleVictim

# --- spaces as JSON --------------------------------------------------------------------------


def _floats(values: np.ndarray) -> list:
    return [v if np.isfinite(v) else ("inf" if v > 0 else "-inf") for v in np.asarray(values, float).ravel().tolist()]


def box_to_json(space: gym.spaces.Box) -> dict[str, Any]:
    """A ``Box`` as plain JSON (infinities as strings)."""
    return {"shape": list(space.shape), "low": _floats(space.low), "high": _floats(space.high), "dtype": str(space.dtype)}


def box_from_json(data: dict[str, Any]) -> gym.spaces.Box:
    shape = tuple(data["shape"])
    low = np.array([float(v) for v in data["low"]], np.float64).reshape(shape)
    high = np.array([float(v) for v in data["high"]], np.float64).reshape(shape)
    dtype = np.dtype(data.get("dtype", "float32"))
    return gym.spaces.Box(low.astype(dtype), high.astype(dtype), shape, dtype=dtype)


# --- this project's victims --------------------------------------------------------------------

VICTIM_KIND = "victim"


def save_victim(path: str | Path, actor: TanhGaussianActor, observation_space: gym.spaces.Box,
                action_space: gym.spaces.Box, meta: dict[str, Any]) -> Path:
    """Save a tanh-Gaussian actor as a victim checkpoint (its mean action is the victim's action)."""
    meta = dict(meta)
    meta.update({
        "architecture": {"type": "tanh-gaussian-mlp", "obs_dim": actor.obs_dim, "act_dim": actor.act_dim,
                         "hidden": actor.trunk[0].out_features, "layers": (len(actor.trunk) - 1) // 2,
                         "log_std_bounds": list(actor.log_std_bounds)},
        "observation_space": box_to_json(observation_space),
        "action_space": box_to_json(action_space),
    })
    return save_checkpoint(path, VICTIM_KIND, {"actor": actor.state_dict()}, meta)


def load_actor(path: str | Path) -> tuple[TanhGaussianActor, dict[str, Any]]:
    """The trainable actor of a victim checkpoint, with the checkpoint's metadata."""
    state, meta = load_checkpoint(path, VICTIM_KIND)
    arch = meta["architecture"]
    actor = TanhGaussianActor(arch["obs_dim"], arch["act_dim"], arch["hidden"], arch["layers"], tuple(arch["log_std_bounds"]))
    try:
        actor.load_state_dict(state["actor"])
    except RuntimeError as exc:
        raise RatError(f"victim checkpoint '{path}' does not match its own architecture; make it again") from exc
    return actor, meta


def load_rat_victim(path: str | Path, name: str | None = None) -> ModuleVictim:
    """Load a victim checkpoint made by ``rat victim train`` (frozen)."""
    actor, meta = load_actor(path)
    return ModuleVictim(actor, box_from_json(meta["observation_space"]), box_from_json(meta["action_space"]),
                        name=name or str(path), meta=meta)


# --- Stable-Baselines3 --------------------------------------------------------------------------

_ACTIVATIONS = {"ReLU": nn.ReLU, "Tanh": nn.Tanh, "ELU": nn.ELU, "LeakyReLU": nn.LeakyReLU, "GELU": nn.GELU,
                "SiLU": nn.SiLU, "Sigmoid": nn.Sigmoid}


def _activation_from_kwargs(policy_kwargs: Any, default: type[nn.Module]) -> type[nn.Module]:
    """Find ``activation_fn`` in SB3's policy_kwargs without unpickling: read the pickle's opcodes."""
    if not isinstance(policy_kwargs, dict) or ":serialized:" not in policy_kwargs:
        return default
    names = []
    for opcode, arg, _ in pickletools.genops(base64.b64decode(policy_kwargs[":serialized:"])):
        if opcode.name in ("SHORT_BINUNICODE", "BINUNICODE", "UNICODE", "GLOBAL") and isinstance(arg, str):
            names.extend(arg.split())
    found = [n for n in names if n in _ACTIVATIONS]
    return _ACTIVATIONS[found[0]] if found else default


def _sequential_from(state: dict[str, torch.Tensor], prefix: str, activation: type[nn.Module],
                     final: type[nn.Module] | None = None) -> nn.Sequential:
    """Rebuild ``Linear, act, Linear, act, ...`` from weights named ``prefix.{i}.weight``."""
    indices = sorted({int(k[len(prefix) + 1:].split(".")[0]) for k in state if k.startswith(prefix + ".")})
    layers: list[nn.Module] = []
    loaded = {}
    for n, i in enumerate(indices):
        w = state[f"{prefix}.{i}.weight"]
        lin = nn.Linear(w.shape[1], w.shape[0])
        loaded[f"{len(layers)}.weight"], loaded[f"{len(layers)}.bias"] = w, state[f"{prefix}.{i}.bias"]
        layers.append(lin)
        if n < len(indices) - 1:
            layers.append(activation())
    if final is not None:
        layers.append(final())
    seq = nn.Sequential(*layers)
    seq.load_state_dict(loaded)
    return seq


class _SB3SACActor(nn.Module):
    def __init__(self, state, activation):
        super().__init__()
        self.latent = _sequential_from(state, "actor.latent_pi", activation)
        self.latent.append(activation())  # SB3's create_mlp ends its latent net with an activation
        self.mu = _sequential_from(state, "actor.mu", activation) if "actor.mu.0.weight" in state else None
        if self.mu is None:
            self.mu = nn.Linear(*state["actor.mu.weight"].T.shape)
            self.mu.load_state_dict({"weight": state["actor.mu.weight"], "bias": state["actor.mu.bias"]})

    def forward(self, obs):
        return torch.tanh(self.mu(self.latent(obs)))


class _SB3PPOActor(nn.Module):
    def __init__(self, state, activation):
        super().__init__()
        self.latent = _sequential_from(state, "mlp_extractor.policy_net", activation)
        self.latent.append(activation())
        self.action_net = nn.Linear(*state["action_net.weight"].T.shape)
        self.action_net.load_state_dict({"weight": state["action_net.weight"], "bias": state["action_net.bias"]})

    def forward(self, obs):
        return self.action_net(self.latent(obs))


def _parse_numpy_text(texts: list, shape: tuple[int, ...]) -> np.ndarray | None:
    """Numbers from numpy's printed form (``"[-1. -1. inf]"`` or a scalar ``"-1.0"``), or None if elided."""
    for text in texts:
        if isinstance(text, (int, float, list)):
            return np.broadcast_to(np.asarray(text, np.float64), shape).copy()
        if not isinstance(text, str) or "..." in text:
            continue
        numbers = [float(t) for t in text.replace("[", " ").replace("]", " ").replace(",", " ").split()]
        if len(numbers) == 1:
            return np.full(shape, numbers[0])
        if len(numbers) == int(np.prod(shape)):
            return np.asarray(numbers).reshape(shape)
    return None


def _sb3_box(data: dict[str, Any], key: str, path: Path) -> gym.spaces.Box:
    """A Box from the readable fields SB3 writes beside the pickled space."""
    space = data.get(key, {})
    if not isinstance(space, dict) or "_shape" not in space or "low" not in space:
        raise RatError(f"'{path}' has a non-Box {key.replace('_', ' ')}; only Box observations and actions are supported")
    try:
        shape = tuple(int(n) for n in space["_shape"])
        low = _parse_numpy_text([space.get("low"), space.get("low_repr")], shape)
        high = _parse_numpy_text([space.get("high"), space.get("high_repr")], shape)
        dtype = np.dtype(space.get("dtype", "float32"))
    except (TypeError, ValueError) as exc:
        raise RatError(f"the {key.replace('_', ' ')} recorded in '{path}' is malformed ({exc}); save the model with "
                       "model.save() and try again") from exc
    if low is None or high is None:
        raise RatError(f"the bounds of the {key.replace('_', ' ')} in '{path}' are not readable; "
                       "wrap the model as a ModuleVictim in Python instead")
    return gym.spaces.Box(low.astype(dtype), high.astype(dtype), shape, dtype=dtype)


def load_sb3_victim(path: str | Path, name: str | None = None) -> ModuleVictim:
    """Load a Stable-Baselines3 SAC/TD3/DDPG/PPO/A2C ``.zip`` (MlpPolicy, Box spaces) as a frozen victim.

    The victim's action is the policy's deterministic action, as ``model.predict(obs,
    deterministic=True)`` gives it.
    """
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as z:
            data = json.loads(z.read("data"))
            state = torch.load(io.BytesIO(z.read("policy.pth")), map_location="cpu", weights_only=True)
    except FileNotFoundError as exc:
        raise RatError(f"no Stable-Baselines3 model at '{path}'; check the path") from exc
    except pickle.UnpicklingError as exc:
        raise RatError(f"the policy.pth in '{path}' holds Python objects besides tensors, which rat never loads "
                       "(loading them could run code from the file); save the model with Stable-Baselines3's "
                       "model.save(), which stores the weights only") from exc
    except (zipfile.BadZipFile, KeyError, json.JSONDecodeError, UnicodeDecodeError, RuntimeError, EOFError,
            ValueError) as exc:
        raise RatError(f"'{path}' is not a readable Stable-Baselines3 model file ({exc.__class__.__name__}); "
                       "save it with model.save() and try again") from exc
    if not isinstance(data, dict):
        raise RatError(f"the 'data' entry of '{path}' is a JSON {type(data).__name__}, not the object "
                       "Stable-Baselines3 writes; save the model with model.save() and try again")
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise RatError(f"the policy.pth in '{path}' is not a state dict of named tensors (it holds a "
                       f"{type(state).__name__}); save the model with model.save() and try again")
    obs_space, act_space = _sb3_box(data, "observation_space", path), _sb3_box(data, "action_space", path)
    kwargs = data.get("policy_kwargs", {})
    if "actor.latent_pi.0.weight" in state:  # SAC
        policy, squashed = _SB3SACActor(state, _activation_from_kwargs(kwargs, nn.ReLU)), True
    elif "actor.mu.0.weight" in state:  # TD3 / DDPG: an MLP ending in tanh
        policy = _sequential_from(state, "actor.mu", _activation_from_kwargs(kwargs, nn.ReLU), final=nn.Tanh)
        squashed = True
    elif "mlp_extractor.policy_net.0.weight" in state and "action_net.weight" in state:  # PPO / A2C
        if "log_std" not in state:
            raise RatError(f"'{path}' is an on-policy model without a Gaussian action head; only Box actions are supported")
        policy, squashed = _SB3PPOActor(state, _activation_from_kwargs(kwargs, nn.Tanh)), False
    else:
        raise RatError(f"'{path}' holds no SB3 MlpPolicy actor this adapter knows (SAC, TD3, DDPG, PPO, A2C)")
    victim = ModuleVictim(policy, obs_space, act_space, name=name or f"sb3:{path}", squashed=squashed,
                          meta={"source": "stable-baselines3", "path": str(path)})
    return victim
