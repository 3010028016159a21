"""Sequence victims: Decision Transformers that act on their recent history.

A Decision Transformer (``transformers.DecisionTransformerModel``, Chen et al. 2021) reads the
last K steps of (return-to-go, state, action) and predicts the next action. As a
:class:`~rat.victims.base.Victim` it keeps that history in a :class:`DTContext`:

- ``initial_context()`` starts an episode: no steps yet, return-to-go = the target return;
- ``act(obs, context)`` appends ``obs`` as the current state (normalised with the checkpoint's own
  statistics) and returns the predicted action; it is differentiable in ``obs``, the only input
  an attacker controls;
- ``update_context(context, obs, action, reward)`` records the step: the state *as the victim saw
  it*, the action it took, and the return-to-go lowered by the true reward.

The model is causal, so only the current state's token depends on the current observation; the victim
runs the tokens before it without gradients and that one token with them (:meth:`DecisionTransformerVictim._split_action`).
Where many observations meet one context (an attacker refining Δ), ``prepare(context)`` runs the past
once for all of them.

The threat model for a sequence victim: each observation is perturbed once, when it is seen,
and the perturbed state stays in the context — the victim never sees the true state of a past
step, because it never saw it. An attacker does not get to rewrite the past; what it changes is
the present observation, whose effect lives on in the context.

Checkpoints load as users have them, in the Hugging Face hub's layout, from a local directory:
``config.json`` and the weights (``model.safetensors``, or ``pytorch_model.bin`` read with
``torch.load(weights_only=True)``), plus ``rat_dt.json`` beside them, which this project defines:
``{"state_mean": [...], "state_std": [...], "target_return": 6000, "return_scale": 1000,
"task": "HalfCheetah-v5"}``. Nothing is downloaded.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from rat.errors import RatError, require
from rat.victims.base import freeze

DT_META = "rat_dt.json"


@dataclass(frozen=True)
class DTContext:
    """The last K − 1 steps of a batch of episodes as the victim saw them, left-padded to a fixed shape.

    The fixed shape lets the contexts of different episodes and steps stack into one batch (an
    attack trains on states drawn from many episodes) and pack into one row of floats
    (:meth:`DecisionTransformerVictim.pack_context`) for a replay buffer.

    Attributes:
        states: ``[B, K-1, obs_dim]`` raw (unnormalised) states seen, oldest first.
        actions: ``[B, K-1, act_dim]`` actions taken.
        returns_to_go: ``[B, K]`` returns-to-go (unscaled); the last one is for the coming step.
        timesteps: ``[B, K]`` episode steps; the last one is for the coming step.
        mask: ``[B, K-1]`` 1 where a past step exists (the first steps of an episode have fewer).
    """

    states: torch.Tensor
    actions: torch.Tensor
    returns_to_go: torch.Tensor
    timesteps: torch.Tensor
    mask: torch.Tensor

    @property
    def length(self) -> int:
        """Past steps held (of the first episode of the batch)."""
        return int(self.mask[0].sum().item())

    def repeat(self, n: int) -> DTContext:
        """One episode's context for a batch of ``n`` observations."""
        return DTContext(*(x.expand(n, *x.shape[1:]) for x in self.fields()))

    def fields(self) -> tuple[torch.Tensor, ...]:
        return self.states, self.actions, self.returns_to_go, self.timesteps, self.mask


@dataclass(frozen=True)
class PastKeysValues:
    """The attention inputs of the tokens before the current state, per block (see ``_split_action``).

    Attributes:
        qkv: per transformer block, its query-key-value projection of the past tokens, ``[B, T, 3·hidden]``.
        mask: ``[B, T]`` 1 where a past token exists.
    """

    qkv: tuple[torch.Tensor, ...]
    mask: torch.Tensor

    def repeat(self, n: int) -> PastKeysValues:
        return PastKeysValues(tuple(x.expand(n, *x.shape[1:]) for x in self.qkv), self.mask.expand(n, -1))


@dataclass(frozen=True)
class PreparedContext:
    """A context whose past has run through the model once (:meth:`DecisionTransformerVictim.prepare`).

    Acting in it runs only the current state's token: the same actions as in the context it was made from (to the split's
    tolerance, :meth:`DecisionTransformerVictim._split_matches_model`), for any number of observations.
    """

    past: PastKeysValues
    timestep: torch.Tensor  #: ``[B, 1]`` the coming step's timestep, as the model reads it

    def repeat(self, n: int) -> PreparedContext:
        return PreparedContext(self.past.repeat(n), self.timestep.expand(n, -1))


class DecisionTransformerVictim(nn.Module):
    """A frozen Decision Transformer as a :class:`~rat.victims.base.Victim` (see the module docstring).

    Args:
        model: the ``DecisionTransformerModel``; it is frozen here.
        observation_space, action_space: what it expects and emits.
        state_mean, state_std: the statistics its states were normalised with in training.
        target_return: the return it is conditioned on at the start of an episode.
        return_scale: returns-to-go are divided by it before they enter the model (1000 in the paper).
        context_length: K, the steps it reads (the paper's 20): K − 1 past ones and the current one.
    """

    def __init__(self, model: nn.Module, observation_space: gym.spaces.Box, action_space: gym.spaces.Box,
                 state_mean: np.ndarray, state_std: np.ndarray, target_return: float, return_scale: float = 1000.0,
                 context_length: int = 20, name: str = "decision-transformer", meta: dict[str, Any] | None = None):
        super().__init__()
        if hasattr(model, "set_attn_implementation"):
            # The weighting network's hypergradient differentiates through the victim twice; the fused CPU
            # attention kernels have no second derivative, the plain one has (and gives the same actions).
            model.set_attn_implementation("eager")
        self.model = freeze(model)
        self.observation_space, self.action_space, self.name = observation_space, action_space, name
        self.meta = dict(meta or {})
        self.target_return, self.return_scale, self.context_length = float(target_return), float(return_scale), context_length
        self.max_timestep = int(model.config.max_ep_len) - 1
        self.register_buffer("state_mean", torch.as_tensor(np.asarray(state_mean), dtype=torch.float32))
        self.register_buffer("state_std", torch.as_tensor(np.asarray(state_std), dtype=torch.float32))
        self.register_buffer("low", torch.as_tensor(action_space.low, dtype=torch.float32))
        self.register_buffer("high", torch.as_tensor(action_space.high, dtype=torch.float32))
        obs_dim, act_dim, past = observation_space.shape[0], action_space.shape[0], context_length - 1
        self._widths = (past * obs_dim, past * act_dim, context_length, context_length, past)
        self.split_forward = self._split_matches_model()  #: see _split_action

    def train(self, mode: bool = True) -> DecisionTransformerVictim:
        return super().train(False)  # dropout would make the victim stochastic

    def initial_context(self, batch_size: int = 1) -> DTContext:
        obs_dim, act_dim, past = self.observation_space.shape[0], self.action_space.shape[0], self.context_length - 1
        zeros = lambda *shape: torch.zeros(batch_size, *shape, device=self.state_mean.device)  # noqa: E731
        return DTContext(zeros(past, obs_dim), zeros(past, act_dim),
                         torch.full((batch_size, self.context_length), self.target_return, device=self.state_mean.device),
                         zeros(self.context_length), zeros(past))

    def act(self, obs: torch.Tensor, context: DTContext | None = None) -> torch.Tensor:
        """The action for the current observations ``[B, obs_dim]`` after ``context`` (a fresh episode if None).

        ``context`` holds one episode (shared by the whole batch) or one per observation.
        """
        action = self._action(obs.float(), context)
        return torch.max(torch.min(action, self.high), self.low)

    def _action(self, obs: torch.Tensor, context: DTContext | PreparedContext | None) -> torch.Tensor:
        """The model's action for ``obs`` after ``context``, before it is clipped to the action space."""
        batch = obs.shape[0]
        if isinstance(context, PreparedContext):
            context = context if context.timestep.shape[0] == batch else context.repeat(batch)
            state = ((obs - self.state_mean) / self.state_std).unsqueeze(1)
            return self._current_action(state, context.timestep, context.past)
        if context is None:
            context = self.initial_context(batch)
        if context.states.shape[0] != batch:
            context = context.repeat(batch)
        inputs = self._inputs(obs, context)
        # the split pays off where a gradient flows back to obs; acting alone, one whole pass is faster
        split = self.split_forward and torch.is_grad_enabled() and obs.requires_grad
        return self._split_action(*inputs) if split else self._model_action(*inputs)

    def prepare(self, context: DTContext) -> DTContext | PreparedContext:
        """``context`` made ready to act on many observations: its past tokens run through the model once, here.

        An attacker refining one observation's Δ acts in the same context at every step; in the prepared
        context each step runs the current state's token alone, where :meth:`act` in ``context`` would run
        the past again each time. A model the split does not reproduce gets ``context`` back.
        """
        if not self.split_forward:
            return context
        placeholder = torch.zeros(context.states.shape[0], self.observation_space.shape[0], device=context.states.device)
        states, actions, rtg, timesteps, mask = self._inputs(placeholder, context)  # the past does not read it
        return PreparedContext(self._past(states, actions, rtg, timesteps, mask), timesteps[:, -1:])

    def _inputs(self, obs: torch.Tensor, context: DTContext) -> tuple[torch.Tensor, ...]:
        """The model's inputs over the K steps, as in training: normalised states, padding zeroed and masked."""
        batch = obs.shape[0]
        mask = torch.cat([context.mask, torch.ones(batch, 1, device=obs.device)], 1)  # [B, K]; padding is 0
        states = (torch.cat([context.states, obs.unsqueeze(1)], 1) - self.state_mean) / self.state_std
        placeholder = torch.zeros(batch, 1, self.action_space.shape[0], device=obs.device)  # not yet taken
        actions = torch.cat([context.actions, placeholder], 1)
        rtg = context.returns_to_go / self.return_scale
        timesteps = (context.timesteps.clamp(max=self.max_timestep) * mask).long()
        return states * mask.unsqueeze(-1), actions * mask.unsqueeze(-1), (rtg * mask).unsqueeze(-1), timesteps, mask

    def _model_action(self, states, actions, rtg, timesteps, mask) -> torch.Tensor:
        """The action as the library's ``DecisionTransformerModel.forward`` computes it (every token at once)."""
        _, action_preds, _ = self.model(
            states=states, actions=actions, rewards=torch.zeros_like(rtg), returns_to_go=rtg, timesteps=timesteps,
            attention_mask=mask.long(), return_dict=False)
        return action_preds[:, -1]

    def _split_action(self, states, actions, rtg, timesteps, mask) -> torch.Tensor:
        """The same action, with the past computed once, without gradients, and only the current state token after.

        The model is causal: the tokens before the current state (the K − 1 past steps and the coming
        return-to-go) do not depend on the current observation, so their keys and values are taken from
        one gradient-free pass, and the current state's token alone runs through the blocks with
        gradients. An attacker's gradient (and the weighting network's second-order one) is the same as
        through the whole model at about half the cost; :meth:`_split_matches_model` checks the two agree.
        """
        past = self._past(states, actions, rtg, timesteps, mask)
        return self._current_action(states[:, -1:], timesteps[:, -1:], past)

    def _past(self, states, actions, rtg, timesteps, mask) -> PastKeysValues:
        """The keys and values of the tokens before the current state, from one pass without gradients."""
        encoder = self.model.encoder
        with torch.no_grad():
            past_tokens = self._tokens(states, actions, rtg, timesteps)[:, :-2]  # up to the coming return-to-go
            past_mask = mask.repeat_interleave(3, dim=1)[:, :-2]
            qkv = []
            hooks = [block.attn.c_attn.register_forward_hook(lambda _m, _i, out: qkv.append(out)) for block in encoder.h]
            try:
                encoder(inputs_embeds=past_tokens, attention_mask=past_mask.long(),
                        position_ids=torch.zeros_like(past_mask, dtype=torch.long))
            finally:
                for hook in hooks:
                    hook.remove()
        return PastKeysValues(tuple(qkv), past_mask)

    def _current_action(self, state, timestep, past: PastKeysValues) -> torch.Tensor:
        """The action from the current state's token (``state`` normalised, ``[B, 1, obs_dim]``) after ``past``."""
        model, encoder = self.model, self.model.encoder
        hidden = model.hidden_size
        x = model.embed_ln(model.embed_state(state) + model.embed_timestep(timestep))
        x = x + encoder.wpe(torch.zeros_like(timestep))  # every token sits at position 0 in the DT
        blocked = torch.cat([past.mask, torch.ones_like(past.mask[:, :1])], 1) == 0  # [B, T]
        heads = model.config.n_head
        split = lambda t: t.reshape(t.shape[0], t.shape[1], heads, -1).transpose(1, 2)  # noqa: E731 [B, h, T, d]
        for layer, (block, qkv) in enumerate(zip(encoder.h, past.qkv)):
            _, past_keys, past_values = qkv.split(hidden, dim=2)
            query, key, value = block.attn.c_attn(block.ln_1(x)).split(hidden, dim=2)
            query, keys, values = split(query), split(torch.cat([past_keys, key], 1)), split(torch.cat([past_values, value], 1))
            scores = (query @ keys.transpose(-1, -2)) * self._attention_scale(layer, query.shape[-1])
            scores = scores.masked_fill(blocked[:, None, None, :], torch.finfo(scores.dtype).min)
            attended = (scores.softmax(-1) @ values).transpose(1, 2).reshape(x.shape)
            x = x + block.attn.c_proj(attended)
            x = x + block.mlp(block.ln_2(x))
        return model.predict_action(encoder.ln_f(x))[:, 0]

    def _tokens(self, states, actions, rtg, timesteps) -> torch.Tensor:
        """The interleaved (return-to-go, state, action) token embeddings, ``[B, 3K, hidden]``, as the model makes them."""
        model, (batch, steps) = self.model, states.shape[:2]
        time = model.embed_timestep(timesteps)
        tokens = torch.stack([model.embed_return(rtg) + time, model.embed_state(states) + time,
                              model.embed_action(actions) + time], dim=2)
        return model.embed_ln(tokens.reshape(batch, 3 * steps, model.hidden_size))

    def _attention_scale(self, layer: int, head_dim: int) -> float:
        config = self.model.config
        scale = head_dim ** -0.5 if getattr(config, "scale_attn_weights", True) else 1.0
        return scale / (layer + 1) if getattr(config, "scale_attn_by_inverse_layer_idx", False) else scale

    def _split_matches_model(self) -> bool:
        """Whether :meth:`_split_action` reproduces the model's own forward on a random context (else it is not used).

        It re-implements the GPT-2 blocks' attention for one token; a model whose blocks compute
        something else (another library version, another attention variant) falls back to the full forward.
        """
        generator = torch.Generator().manual_seed(0)
        obs_dim, act_dim = self.observation_space.shape[0], self.action_space.shape[0]
        context = self.initial_context(3)
        try:
            with torch.no_grad():
                for _ in range(self.context_length + 1):  # fills the context, then slides it
                    obs = torch.randn(3, obs_dim, generator=generator).to(self.state_mean.device) * self.state_std + self.state_mean
                    inputs = self._inputs(obs, context)
                    if not torch.allclose(self._split_action(*inputs), self._model_action(*inputs), atol=1e-5, rtol=1e-4):
                        return False
                    action = torch.rand(3, act_dim, generator=generator).to(obs.device) * 2 - 1
                    context = self.update_context(context, obs, action, torch.randn(3, generator=generator))
        except (AttributeError, RuntimeError, TypeError, ValueError):
            return False
        return True

    forward = act

    def update_context(self, context: DTContext, obs: torch.Tensor, action: torch.Tensor, reward: torch.Tensor
                       ) -> DTContext:
        """The context after a step: the state as seen, the action taken, the return-to-go lowered by the true reward."""
        obs, action = obs.detach().float(), action.detach().float()
        reward = torch.as_tensor(reward, dtype=torch.float32, device=obs.device).reshape(-1)
        shift = lambda old, new: torch.cat([old[:, 1:], new.unsqueeze(1).to(old.dtype)], 1)  # noqa: E731
        return DTContext(shift(context.states, obs), shift(context.actions, action),
                         shift(context.returns_to_go, context.returns_to_go[:, -1] - reward),
                         shift(context.timesteps, context.timesteps[:, -1] + 1),
                         shift(context.mask, torch.ones(obs.shape[0], device=obs.device)))

    @property
    def context_size(self) -> int:
        """Floats in one packed context (see :meth:`pack_context`)."""
        return sum(self._widths)

    def pack_context(self, context: DTContext) -> torch.Tensor:
        """``context`` as one row of floats per episode, ``[B, context_size]`` (for a replay buffer)."""
        return torch.cat([x.reshape(x.shape[0], -1).float() for x in context.fields()], 1)

    def unpack_context(self, packed: torch.Tensor) -> DTContext:
        """The contexts of ``[B, context_size]`` rows made by :meth:`pack_context`."""
        obs_dim, act_dim, past = self.observation_space.shape[0], self.action_space.shape[0], self.context_length - 1
        states, actions, rtg, timesteps, mask = torch.split(packed.float(), self._widths, 1)
        batch = packed.shape[0]
        return DTContext(states.reshape(batch, past, obs_dim), actions.reshape(batch, past, act_dim), rtg,
                         timesteps.round(), mask)


# --- checkpoints in the hub's layout ----------------------------------------------------------------------------


def save_decision_transformer(directory: str | Path, model: nn.Module, state_mean, state_std, target_return: float,
                              return_scale: float = 1000.0, **meta) -> Path:
    """Write ``model`` in the hub's layout (``config.json`` + ``model.safetensors``) with ``rat_dt.json``."""
    directory = Path(directory)
    model.save_pretrained(directory, safe_serialization=True)
    (directory / DT_META).write_text(json.dumps({
        "state_mean": np.asarray(state_mean, float).tolist(), "state_std": np.asarray(state_std, float).tolist(),
        "target_return": float(target_return), "return_scale": float(return_scale), **meta}, indent=1))
    return directory


def load_decision_transformer(directory: str | Path, name: str | None = None) -> DecisionTransformerVictim:
    """A Decision Transformer from a local directory in the hub's layout, with ``rat_dt.json`` beside it."""
    transformers = require("transformers", "dt")
    from safetensors.torch import load_file

    directory = Path(directory)
    if not (directory / "config.json").is_file():
        raise RatError(f"no Decision Transformer at '{directory}': expected config.json and weights in the hub's layout")
    if not (directory / DT_META).is_file():
        raise RatError(f"'{directory}' lacks {DT_META} (state_mean, state_std, target_return): write it beside "
                       "config.json; the hub's checkpoints publish these numbers in their model cards")
    try:
        meta = json.loads((directory / DT_META).read_text())
        settings = json.loads((directory / "config.json").read_text())
        for key in ("bos_token_id", "eos_token_id"):  # GPT-2's, in the hub's configs; a DT has no vocabulary
            if isinstance(settings.get(key), int) and settings[key] >= settings.get("vocab_size", 1):
                settings[key] = None
        config = transformers.DecisionTransformerConfig.from_dict(settings)
    except (json.JSONDecodeError, UnicodeDecodeError, OSError, ValueError) as exc:
        raise RatError(f"the configuration in '{directory}' is not readable ({exc.__class__.__name__}); "
                       "restore config.json and rat_dt.json") from exc
    if getattr(config, "model_type", None) != "decision_transformer":
        raise RatError(f"'{directory}/config.json' is a '{getattr(config, 'model_type', '?')}' model, not a "
                       "Decision Transformer")
    if (directory / "model.safetensors").is_file():
        state = load_file(str(directory / "model.safetensors"))
    elif (directory / "pytorch_model.bin").is_file():
        try:
            state = torch.load(directory / "pytorch_model.bin", map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - pickles with code are refused by weights_only
            raise RatError(f"'{directory}/pytorch_model.bin' holds more than tensors, which rat never loads; "
                           "convert it to model.safetensors") from exc
    else:
        raise RatError(f"no weights in '{directory}': expected model.safetensors or pytorch_model.bin")
    model = transformers.DecisionTransformerModel(config)
    missing, unexpected = model.load_state_dict(state, strict=False)
    if [k for k in missing if not k.endswith("attn.bias") and not k.endswith("attn.masked_bias")] or unexpected:
        raise RatError(f"the weights in '{directory}' do not match its config.json (missing {len(missing)}, "
                       f"unexpected {len(unexpected)} tensors)")
    obs_dim, act_dim = int(config.state_dim), int(config.act_dim)
    observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float64)
    action_space = gym.spaces.Box(-1.0, 1.0, (act_dim,), np.float32)
    for key, size in (("state_mean", obs_dim), ("state_std", obs_dim)):
        if len(meta.get(key, [])) != size:
            raise RatError(f"{DT_META} in '{directory}' needs {key} of length {size} (the state size)")
    return DecisionTransformerVictim(model, observation_space, action_space, meta["state_mean"], meta["state_std"],
                                     meta.get("target_return", 0.0), meta.get("return_scale", 1000.0),
                                     int(meta.get("context_length", 20)),
                                     name=name or str(directory), meta={"method": "decision-transformer"} | {
                                         k: v for k, v in meta.items() if k not in ("state_mean", "state_std")})
