"""Making Decision Transformer victims: expert data from a trained agent, then a Decision Transformer on it.

The paper's sequence victims are the Hugging Face hub's expert Decision Transformers, trained on
D4RL's expert data. Nothing may be downloaded here, so the project makes its own, the same way:

1. an expert: SAC on the task reward (``rat victim train --method sac``, a Gymnasium MuJoCo task);
2. :func:`collect_expert_data`: its episodes, actions with a little Gaussian noise (D4RL's expert
   data come from a stochastic SAC policy too), saved as safetensors;
3. :func:`train_dt`: a ``transformers.DecisionTransformerModel`` of the hub checkpoints' shape
   (hidden size 128, 3 layers, 1 head, K = 20, ReLU, dropout 0.1, tanh actions), trained as Chen et
   al. (2021) did: segments of K steps, states normalised by the data's statistics, returns-to-go
   divided by 1000, mean squared error of the predicted actions, AdamW with a linear warm-up. It
   runs in a :class:`~rat.runs.Run` directory, checkpoints and resumes, and ends by evaluating the
   Decision Transformer conditioned on the data's best return and saving it in the hub's layout
   (``victim/config.json``, ``victim/model.safetensors``, ``victim/rat_dt.json``).
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors.numpy import load_file, save_file
from tqdm.auto import tqdm

from rat import seeds
from rat.envs import LOCOMOTION_TASKS, make_task
from rat.errors import RatError, require
from rat.eval import EvalResult, evaluate
from rat.loop import TrainingLoop
from rat.runs import Run, git_commit, restore_rng_state, rng_state, seed_everything
from rat.victims.base import Victim, numpy_policy
from rat.victims.sequence import DecisionTransformerVictim, save_decision_transformer

#: D4RL's reference returns (Fu et al. 2020, ``d4rl/infos.py``): an expert's and a random policy's episode
#: returns, the 100 and the 0 of its normalised score. D4RL's medium data come from a policy stopped at
#: about a third of the expert's return; a medium policy scores about 33 on that scale.
D4RL_REFERENCE = {
    "HalfCheetah-v5": {"expert": 12135.0, "random": -280.178953},
    "Walker2d-v5": {"expert": 4592.3, "random": 1.629008},
}


def d4rl_score(task: str, episode_return: float) -> float:
    """D4RL's normalised score of a return: 0 a random policy, 100 its expert."""
    ref = D4RL_REFERENCE[task]
    return 100 * (episode_return - ref["random"]) / (ref["expert"] - ref["random"])


# --- expert data ---------------------------------------------------------------------------------


@dataclass
class ExpertData:
    """Episodes of an agent, concatenated: ``obs [N, d]``, ``actions [N, a]``, ``rewards [N]``, and
    ``episode_starts`` (the index where each episode begins)."""

    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    episode_starts: np.ndarray
    meta: dict

    @property
    def episode_returns(self) -> np.ndarray:
        return np.add.reduceat(self.rewards, self.episode_starts)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        save_file({"obs": self.obs.astype(np.float32), "actions": self.actions.astype(np.float32),
                   "rewards": self.rewards.astype(np.float32), "episode_starts": self.episode_starts.astype(np.int64)},
                  str(path), metadata={"meta": json.dumps(self.meta)})
        return path

    @classmethod
    def load(cls, path: str | Path) -> ExpertData:
        from safetensors import safe_open

        try:
            arrays = load_file(str(path))
            with safe_open(str(path), "np") as f:
                meta = json.loads((f.metadata() or {}).get("meta", "{}"))
        except Exception as exc:  # noqa: BLE001 - a truncated or foreign file
            raise RatError(f"'{path}' is not expert data written by rat ({exc.__class__.__name__}); "
                           "collect it again with rat victim dt") from exc
        missing = {"obs", "actions", "rewards", "episode_starts"} - set(arrays)
        if missing:
            raise RatError(f"'{path}' lacks {', '.join(sorted(missing))}; collect it again with rat victim dt")
        return cls(arrays["obs"], arrays["actions"], arrays["rewards"], arrays["episode_starts"], meta)


def collect_expert_data(expert: Victim, task: str, episodes: int, seed: int, noise: float = 0.1,
                        progress: bool = False) -> ExpertData:
    """``episodes`` episodes of ``expert`` on ``task``; executed actions get N(0, noise²) noise, clipped."""
    env, rng = make_task(task, seed=seed), np.random.default_rng(seed)
    policy = numpy_policy(expert)
    low, high = env.action_space.low, env.action_space.high
    obs_list, act_list, rew_list, starts = [], [], [], []
    for episode in tqdm(range(episodes), desc=f"expert data {task}", disable=not progress, leave=False):
        obs, _ = env.reset(seed=seed + episode)
        policy.reset()
        starts.append(len(rew_list))
        done = False
        while not done:
            action = np.clip(policy(obs) + noise * rng.standard_normal(low.shape), low, high).astype(np.float32)
            next_obs, reward, terminated, truncated, _ = env.step(action)
            obs_list.append(obs)
            act_list.append(action)
            rew_list.append(reward)
            obs, done = next_obs, terminated or truncated
    env.close()
    data = ExpertData(np.asarray(obs_list, np.float32), np.asarray(act_list, np.float32),
                      np.asarray(rew_list, np.float32), np.asarray(starts, np.int64),
                      {"task": task, "expert": expert.name, "episodes": episodes, "noise": noise, "seed": seed})
    data.meta["mean_return"] = float(data.episode_returns.mean())
    return data


# --- training ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class DTConfig:
    """How to train a Decision Transformer victim (defaults: the hub checkpoints' shape, DT's recipe)."""

    task: str = "HalfCheetah-v5"  #: Gymnasium MuJoCo task
    expert: str = ""  #: the victim spec of the expert whose episodes are the data (e.g. a SAC victim's run)
    data: str = ""  #: or expert data already collected (``ExpertData``'s safetensors)
    data_episodes: int = 100  #: expert episodes to collect
    data_noise: float = 0.1  #: std of the Gaussian noise on the expert's executed actions
    seed: int = 0  #: seeds the data's episodes, the network and the batches
    hidden: int = 128  #: hidden size (the hub checkpoints': 128)
    layers: int = 3  #: transformer blocks
    heads: int = 1  #: attention heads
    context_length: int = 20  #: K, the steps the model reads
    max_ep_len: int = 1000  #: longest episode (timestep embeddings)
    dropout: float = 0.1  #: dropout in training
    return_scale: float = 1000.0  #: returns-to-go are divided by it
    batch_size: int = 64  #: segments per update
    lr: float = 1e-4  #: AdamW learning rate
    weight_decay: float = 1e-4  #: AdamW weight decay
    warmup_steps: int = 2_000  #: updates of the linear learning-rate warm-up
    grad_clip: float = 0.25  #: gradient-norm clip
    updates: int = 20_000  #: gradient updates
    target_return: float | None = None  #: what the victim is conditioned on (default: the data's best return)
    eval_every: int = 5_000  #: updates between evaluations
    eval_every_episodes: int = 3  #: episodes of each evaluation during training
    eval_episodes: int = 10  #: episodes of the final evaluation
    checkpoint_every: int = 1_000  #: updates between checkpoints
    device: str = "cpu"  #: cpu or cuda

    def __post_init__(self):
        if self.task not in LOCOMOTION_TASKS:
            raise RatError(f"Decision Transformer victims are made for {', '.join(LOCOMOTION_TASKS)}, not '{self.task}'")
        for name in ("hidden", "layers", "heads", "context_length", "batch_size", "updates", "eval_every",
                     "eval_episodes", "checkpoint_every", "max_ep_len", "data_episodes"):
            if getattr(self, name) <= 0:
                raise RatError(f"{name.replace('_', '-')} must be positive, got {getattr(self, name)}")
        if self.data_noise < 0:
            raise RatError(f"data-noise must not be negative, got {self.data_noise}")


def dt_model(obs_dim: int, act_dim: int, cfg: DTConfig):
    """A fresh ``DecisionTransformerModel`` of ``cfg``'s shape."""
    transformers = require("transformers", "dt")
    config = transformers.DecisionTransformerConfig(
        state_dim=obs_dim, act_dim=act_dim, hidden_size=cfg.hidden, n_layer=cfg.layers, n_head=cfg.heads,
        n_inner=4 * cfg.hidden, activation_function="relu", max_ep_len=cfg.max_ep_len, n_positions=1024,
        resid_pdrop=cfg.dropout, embd_pdrop=cfg.dropout, attn_pdrop=cfg.dropout, action_tanh=True,
        bos_token_id=None, eos_token_id=None)  # GPT-2's token ids mean nothing to a model without a vocabulary
    return transformers.DecisionTransformerModel(config)


class Segments:
    """Batches of K-step segments of the data, each ending at a uniformly drawn step and left-padded
    where its episode began later — the shape in which the victim meets its history when acting."""

    def __init__(self, data: ExpertData, cfg: DTConfig):
        self.k, n = cfg.context_length, len(data.rewards)
        ends = np.append(data.episode_starts[1:], n)
        self.start = np.repeat(data.episode_starts, ends - data.episode_starts)  # each step's episode start
        returns_to_go = np.zeros(n, np.float64)
        for s, e in zip(data.episode_starts, ends):
            returns_to_go[s:e] = np.cumsum(data.rewards[s:e][::-1])[::-1]
        self.mean, self.std = data.obs.mean(0), data.obs.std(0) + 1e-6
        self.obs = ((data.obs - self.mean) / self.std).astype(np.float32)
        self.actions = data.actions.astype(np.float32)
        self.rtg = (returns_to_go / cfg.return_scale).astype(np.float32)
        self.timesteps = np.arange(n) - self.start

    def batch(self, size: int, rng: np.random.Generator, device) -> dict[str, torch.Tensor]:
        end = rng.integers(0, len(self.obs), size=size)
        idx = end[:, None] - (self.k - 1) + np.arange(self.k)  # [B, K]
        mask = idx >= self.start[end][:, None]
        idx = np.where(mask, idx, end[:, None])  # padded positions read any valid row, then are zeroed
        m = mask.astype(np.float32)
        t = lambda x: torch.as_tensor(x, device=device)  # noqa: E731
        return {"states": t(self.obs[idx] * m[..., None]), "actions": t(self.actions[idx] * m[..., None]),
                "returns_to_go": t((self.rtg[idx] * m)[..., None]), "timesteps": t(self.timesteps[idx] * mask).long(),
                "attention_mask": t(mask).long(), "rewards": t(np.zeros((size, self.k, 1), np.float32))}


class DTTrainer:
    """Decision Transformer training, one update at a time (a :class:`~rat.loop.Trainer`)."""

    kind = "dt-run"

    def __init__(self, cfg: DTConfig, data: ExpertData, rng: np.random.Generator):
        self.cfg, self.data, self.rng, self.device = cfg, data, rng, torch.device(cfg.device)
        self.segments = Segments(data, cfg)
        self.model = dt_model(data.obs.shape[1], data.actions.shape[1], cfg).to(self.device)
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer,
                                                           lambda u: min((u + 1) / cfg.warmup_steps, 1.0))
        self.target_return = float(cfg.target_return if cfg.target_return is not None else data.episode_returns.max())
        self.step, self.finished, self.losses = 0, False, []

    def advance(self) -> dict[str, float] | None:
        self.model.train()
        batch = self.segments.batch(self.cfg.batch_size, self.rng, self.device)
        _, action_preds, _ = self.model(**batch, return_dict=False)
        mask = batch["attention_mask"].float().unsqueeze(-1)
        loss = (((action_preds - batch["actions"]) ** 2) * mask).sum() / (mask.sum() * action_preds.shape[-1])
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.cfg.grad_clip)
        self.optimizer.step()
        self.scheduler.step()
        self.losses.append(loss.item())
        self.step += 1
        if self.step % 100 == 0 or self.step == self.cfg.updates:
            loss, self.losses = float(np.mean(self.losses)), []
            return {"action_loss": loss, "lr": self.scheduler.get_last_lr()[0]}
        return None

    def victim(self, name: str = "decision-transformer") -> DecisionTransformerVictim:
        """The model as it is now, frozen in a copy, as a victim."""
        env = make_task(self.cfg.task)
        victim = DecisionTransformerVictim(copy.deepcopy(self.model).cpu(), env.observation_space, env.action_space,
                                           self.segments.mean, self.segments.std, self.target_return,
                                           self.cfg.return_scale, self.cfg.context_length, name=name)
        env.close()
        return victim

    def evaluate(self) -> dict[str, float]:
        cfg = self.cfg
        res = evaluate(numpy_policy(self.victim()), make_task(cfg.task, seed=cfg.seed + seeds.VICTIM_EVAL_ENV),
                       cfg.eval_every_episodes, seed=cfg.seed + seeds.VICTIM_EVAL_ENV + self.step)
        return {"eval_return": res.mean_return}

    def state_dict(self) -> dict:
        return {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                "scheduler": {"last_epoch": torch.tensor(self.scheduler.last_epoch)}, "rng": rng_state(self.rng)}

    def load_state_dict(self, state: dict, meta: dict) -> None:
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.last_epoch = int(state["scheduler"]["last_epoch"])
        self.scheduler._last_lr = [g["lr"] for g in self.optimizer.param_groups]
        restore_rng_state(self.rng, state["rng"])
        self.step = int(meta["step"])

    def checkpoint_meta(self) -> dict:
        return {}


def check_data_source(config: DTConfig) -> None:
    """One of ``expert`` and ``data``, and the data file where one is named (checked before anything is written)."""
    if bool(config.expert) == bool(config.data):
        raise RatError("give the expert to collect data from (--expert) or data already collected (--data), one of the two")
    if config.data and not Path(config.data).is_file():
        raise RatError(f"no expert data at '{config.data}'; give a file written by rat victim dt, or --expert")


def expert_data(config: DTConfig, run_dir: Path, progress: bool = True) -> ExpertData:
    """The data of ``config``: loaded from ``config.data``, or collected from ``config.expert`` once per run."""
    check_data_source(config)
    if config.data:
        data = ExpertData.load(config.data)
    else:
        path = run_dir / "expert-data.safetensors"
        if not path.exists():  # a resumed run reuses its data
            from rat.victims import check_compatible, load_victim

            expert = load_victim(config.expert)
            check_compatible(expert, make_task(config.task), f"task '{config.task}'")
            collected = collect_expert_data(expert, config.task, config.data_episodes, config.seed + seeds.FRESH_ENV,
                                            config.data_noise, progress)
            collected.save(path.with_suffix(".partial"))
            path.with_suffix(".partial").replace(path)
        data = ExpertData.load(path)
    if data.meta.get("task", config.task) != config.task:
        raise RatError(f"the expert data are of {data.meta['task']}, not {config.task}; give the matching --task")
    return data


def train_dt(config: DTConfig, out: str | Path, progress: bool = True) -> tuple[Path, EvalResult]:
    """Collect expert data and train a Decision Transformer on it in run directory ``out`` (resuming if
    interrupted). Returns the hub-layout directory of the victim (``out/victim``) and its clean evaluation.
    """
    check_data_source(config)
    run = Run(out, config)
    data = expert_data(config, run.dir, progress)
    trainer = DTTrainer(config, data, seed_everything(config.seed))
    loop = TrainingLoop(run, trainer, config.updates, eval_every=config.eval_every,
                        checkpoint_every=config.checkpoint_every, checkpoint_at_boundary=True,
                        desc=f"decision transformer {config.task}", progress=progress)
    loop.resume()
    loop.run()
    victim = trainer.victim()
    env = make_task(config.task, seed=config.seed + seeds.FRESH_ENV)  # episodes never seen in training
    result = evaluate(numpy_policy(victim), env, config.eval_episodes, seed=seeds.VICTIM_FINAL + config.seed,
                      progress=progress)
    run.logger.log(trainer.step, {"final_return": result.mean_return})
    directory = save_decision_transformer(
        run.dir / "victim", victim.model, trainer.segments.mean, trainer.segments.std, trainer.target_return,
        config.return_scale, context_length=config.context_length, task=config.task, commit=git_commit(),
        train_seconds=round(loop.total_seconds, 1), config=run.config,
        data={k: data.meta.get(k) for k in ("expert", "episodes", "noise", "mean_return")} | {
            "transitions": int(len(data.rewards)), "best_return": float(data.episode_returns.max())},
        clean_eval={"episodes": result.episodes, "mean_return": result.mean_return, "std_return": result.std_return},
        d4rl_reference=D4RL_REFERENCE[config.task], d4rl_score=round(d4rl_score(config.task, result.mean_return), 1))
    return directory, result

