"""The baselines of the paper's table 1, behind the same threat model and evaluation as RAT.

- ``random``: Δ uniform in the ε-ball (no training).
- ``sa-rl`` (Zhang et al. 2021): an RL adversary in the state-adversarial MDP of the paper's
  lemma 3.1, :class:`StateAdversaryEnv`: its action is the perturbation, the frozen victim acts
  on the perturbed observation, the reward is the target reward of the victim's transition.
- ``pa-ad`` (Sun et al. 2022): an RL *director* in :class:`DirectorEnv` chooses a direction in
  the victim's action space; the actor (:func:`rat.attacks.gradient.directed_perturbation`)
  finds the perturbation that moves the victim's action that way.
- ``mad``: maximal action difference, untargeted (no training), for the robust-training tables.

SA-RL and PA-AD learn with Stable-Baselines3's PPO at the paper's table 6 settings
(:class:`PPOConfig`), from either reward of :func:`reward_source`: the true target reward
(the "oracle" variants) or r̂ learned from exactly the labels of a label store — the labels
of the RAT run they are compared with. Both adversary MDPs are plain gymnasium environments, so
any other PPO can train them too.

A trained baseline is a run directory like RAT's: ``config.json``, ``metrics.csv`` (with the same
``eval_success_rate`` column), ``checkpoint.*`` while training (resume by running again),
``adversary.*`` (weights in safetensors, metadata in JSON; loading never unpickles), and
``report.json``. :func:`load_attack` turns any of them, RAT's included, into ``obs -> Δ``.
"""

from __future__ import annotations

import contextlib
import json
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import gymnasium as gym
import numpy as np
import torch

from rat.attacks.gradient import directed_perturbation, mad_perturbation
from rat.attacks.threat import check_budget, perturb, project, random_delta
from rat.checkpoint import load_checkpoint, read_meta, save_checkpoint
from rat.envs.targets import TargetBehaviour
from rat.errors import RatError
from rat.preferences.reward_model import RewardEnsemble, RewardModelConfig
from rat.preferences.store import LabelStore
from rat.runs import Run, seed_everything, to_jsonable
from rat.victims.base import Victim, check_compatible

BASELINES = ("random", "sa-rl", "pa-ad", "mad")
TRAINED = ("sa-rl", "pa-ad")

RewardFn = Callable[[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]], float]


# --- rewards: the true target reward, or r̂ from a label set ------------------------------------------


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


# --- the adversary MDPs ---------------------------------------------------------------------------------


class _AdversaryMDP(gym.Env):
    """The environment seen by an RL adversary: observation = true state, the victim acts on s̃."""

    metadata = {"render_modes": []}

    def __init__(self, env: gym.Env, victim: Victim, reward: RewardFn, target: TargetBehaviour, epsilon: float,
                 norm: str = "linf"):
        check_budget(epsilon, norm)
        check_compatible(victim, env)
        self.env, self.victim, self.reward, self.target = env, victim, reward, target
        self.epsilon, self.norm = float(epsilon), norm
        self.observation_space = env.observation_space
        self._obs: np.ndarray | None = None

    def perturbation(self, obs: torch.Tensor, action: np.ndarray) -> torch.Tensor:
        """Δ in the unit ball for the adversary's ``action`` at the true observation ``obs [1, d]``."""
        raise NotImplementedError

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._obs, info = self.env.reset(seed=seed, options=options)
        return self._obs, info

    def step(self, action: np.ndarray):
        s = torch.as_tensor(self._obs, dtype=torch.float32).unsqueeze(0)
        delta = self.perturbation(s, np.asarray(action, np.float32))
        with torch.no_grad():
            victim_action = self.victim.act(perturb(s, delta, self.epsilon, self.norm)).squeeze(0).numpy()
        next_obs, _, terminated, truncated, info = self.env.step(victim_action)
        reward = self.reward(self._obs, victim_action, next_obs, info)
        info = dict(info, victim_action=victim_action, target_success=self.target.success(info),
                    perturbation=(self.epsilon * delta.squeeze(0)).numpy())
        self._obs = next_obs
        return next_obs, float(reward), terminated, truncated, info

    def close(self):
        self.env.close()


class StateAdversaryEnv(_AdversaryMDP):
    """SA-RL's state-adversarial MDP: action Δ̂ ∈ [−1, 1]^d, perturbation ε·P(Δ̂), reward r(s, a_victim)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        dim = self.observation_space.shape[0]
        self.action_space = gym.spaces.Box(-1.0, 1.0, (dim,), np.float32)

    def perturbation(self, obs, action):
        return project(torch.as_tensor(action, dtype=torch.float32).unsqueeze(0), self.norm)


class DirectorEnv(_AdversaryMDP):
    """PA-AD's director MDP: action d ∈ [−1, 1]^|A| (a direction in the victim's action space).

    The actor turns d into the perturbation maximising cos(μ(s̃) − μ(s), d) + λ‖μ(s̃) − μ(s)‖
    by ``actor_steps`` gradient steps from a random start (1: the paper's FGSM).
    """

    def __init__(self, *args, lam: float = 1.0, actor_steps: int = 1, **kwargs):
        super().__init__(*args, **kwargs)
        self.lam, self.actor_steps = lam, actor_steps
        self.action_space = gym.spaces.Box(-1.0, 1.0, self.env.action_space.shape, np.float32)

    def perturbation(self, obs, action):
        direction = torch.as_tensor(action, dtype=torch.float32).unsqueeze(0)
        return directed_perturbation(self.victim, obs, direction, self.epsilon, self.norm, self.lam,
                                     self.actor_steps, self.np_random)  # random starts follow reset(seed=...)


# --- PPO ---------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PPOConfig:
    """PPO for SA-RL and PA-AD (defaults: the paper's table 6)."""

    total_steps: int = 1_000_000  #: environment steps
    learning_rate: float = 5e-5
    batch_size: int = 32  #: minibatch
    n_steps: int = 2048  #: rollout length per update
    n_epochs: int = 10
    clip_range: float = 0.2
    gamma: float = 0.99
    gae_lambda: float = 0.95
    target_kl: float = 0.01
    ent_coef: float = 0.0
    hidden: int = 256  #: width of the 3 hidden layers of policy and value networks
    layers: int = 3
    lam: float = 1.0  #: PA-AD's λ
    actor_steps: int = 1  #: PA-AD's actor: 1 = FGSM from a random start, more = PGD
    eval_every: int = 10_000  #: steps between attack evaluations (rounded up to whole rollouts)
    eval_episodes: int = 10
    final_eval_episodes: int = 30

    def __post_init__(self):
        for name in ("total_steps", "batch_size", "n_steps", "n_epochs", "hidden", "layers", "actor_steps",
                     "eval_every", "eval_episodes", "final_eval_episodes"):
            if getattr(self, name) <= 0:
                raise RatError(f"{name.replace('_', '-')} must be positive, got {getattr(self, name)}")
        if not self.learning_rate > 0:
            raise RatError(f"learning-rate must be positive, got {self.learning_rate}")


def _policy_kwargs(cfg: PPOConfig) -> dict:
    arch = [cfg.hidden] * cfg.layers
    return {"net_arch": {"pi": arch, "vf": arch}, "activation_fn": torch.nn.Tanh}


def _ppo(env: gym.Env, cfg: PPOConfig, seed: int):
    from stable_baselines3 import PPO

    return PPO("MlpPolicy", env, learning_rate=cfg.learning_rate, n_steps=cfg.n_steps, batch_size=cfg.batch_size,
                   n_epochs=cfg.n_epochs, gamma=cfg.gamma, gae_lambda=cfg.gae_lambda, clip_range=cfg.clip_range,
                   ent_coef=cfg.ent_coef, target_kl=cfg.target_kl, policy_kwargs=_policy_kwargs(cfg), seed=seed,
                   device="cpu", verbose=0)


def _policy_network(observation_space: gym.spaces.Box, action_space: gym.spaces.Box, cfg: PPOConfig):
    """SB3's actor-critic policy rebuilt from shapes (for loading saved weights without unpickling)."""
    from stable_baselines3.common.policies import ActorCriticPolicy

    policy = ActorCriticPolicy(observation_space, action_space, lambda _: 0.0, **_policy_kwargs(cfg))
    return policy.eval()


def ppo_direction(policy) -> Callable[[np.ndarray], np.ndarray]:
    """The deterministic action (mean, clipped to the action space) of an SB3 policy, for one observation."""

    def act(obs: np.ndarray) -> np.ndarray:
        action, _ = policy.predict(np.asarray(obs, np.float32), deterministic=True)
        return np.clip(action, policy.action_space.low, policy.action_space.high)

    return act


# --- attacks as functions obs -> Δ ---------------------------------------------------------------------------


def random_attack(dim: int, norm: str, seed: int) -> Callable[[np.ndarray], np.ndarray]:
    rng = np.random.default_rng(seed)
    return lambda obs: random_delta(rng, dim, norm)


def mad_attack(victim: Victim, epsilon: float, norm: str, seed: int, steps: int = 10):
    rng = np.random.default_rng(seed)

    def delta(obs: np.ndarray) -> np.ndarray:
        s = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
        return mad_perturbation(victim, s, epsilon, norm, steps, rng).squeeze(0).double().numpy()

    return delta


def sarl_attack(policy) -> Callable[[np.ndarray], np.ndarray]:
    act = ppo_direction(policy)
    return lambda obs: act(obs).astype(np.float64)


def paad_attack(policy, victim: Victim, epsilon: float, norm: str, lam: float, steps: int, seed: int):
    rng, direct = np.random.default_rng(seed), ppo_direction(policy)

    def delta(obs: np.ndarray) -> np.ndarray:
        s = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
        d = torch.as_tensor(direct(obs), dtype=torch.float32).unsqueeze(0)
        return directed_perturbation(victim, s, d, epsilon, norm, lam, steps, rng).squeeze(0).double().numpy()

    return delta


# --- training a baseline ------------------------------------------------------------------------------------------


def train_baseline(method: str, victim: Victim, target: TargetBehaviour, make_env: Callable[[int], gym.Env],
                   out: str | Path, epsilon: float = 0.1, norm: str = "linf", seed: int = 0,
                   ppo: PPOConfig = PPOConfig(), labels: str | Path | None = None,
                   reward_config: RewardModelConfig = RewardModelConfig(), describe: dict | None = None,
                   progress: bool = True) -> dict:
    """Train (SA-RL, PA-AD) or set up (random, MAD) a baseline attack and evaluate it; resumable from ``out``.

    Args:
        labels: a label store; SA-RL and PA-AD then learn from r̂ trained on exactly its labels.
            Without it they use the true target reward (the oracle variants).

    Returns the report (also ``out/report.json``); the attack loads with :func:`load_attack`.
    """
    from rat.attacks.rat import evaluate_attack

    if method not in BASELINES:
        raise RatError(f"unknown baseline '{method}'; use one of: {', '.join(BASELINES)}")
    check_budget(epsilon, norm)
    if labels is not None and method not in TRAINED:
        raise RatError(f"'{method}' does not learn, so it takes no labels; drop --labels")
    env = make_env(seed)
    check_compatible(victim, env, f"task '{describe['task']}'" if describe and "task" in describe else "the environment")
    variant = "oracle" if labels is None and method in TRAINED else ("preference" if labels is not None else "none")
    config = {"method": method, "variant": variant, "epsilon": epsilon, "norm": norm, "seed": seed,
              "label_store": str(labels) if labels else None, **({"ppo": to_jsonable(ppo)} if method in TRAINED else {}),
              **(describe or {}), "target": target.name}
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    started = time.perf_counter()
    ensemble, reward_metrics = (None, {}) if labels is None else learn_reward(labels, obs_dim, act_dim,
                                                                           reward_config, seed, cache=True)
    run = Run(out, config)  # made once the inputs are known good, so a mistake leaves nothing behind
    seed_everything(seed)
    meta = {**config, "obs_dim": obs_dim, "act_dim": act_dim}
    extra = {k: v for k, v in reward_metrics.items() if k != "label_ids"}

    if method in TRAINED:
        if labels is not None:
            (run.dir / "labels_used.json").write_text(json.dumps(reward_metrics["label_ids"]))
        policy, extra["ppo_updates"] = _train_ppo(method, run, env, victim, target, reward_source(target, ensemble),
                                                  epsilon, norm, seed, ppo, make_env, progress)
        attack = _trained_attack(method, policy, victim, epsilon, norm, ppo, seed)
        save_checkpoint(run.dir / "adversary", "baseline-adversary", {"policy": policy.state_dict()}, meta)
    else:
        save_checkpoint(run.dir / "adversary", "baseline-adversary", {}, meta)
        attack = load_attack(run.dir, victim)[0]

    final = evaluate_attack(victim, attack, make_env(seed + 7), target, epsilon, norm,
                            ppo.final_eval_episodes, seed=2 * 10**7)
    if not final.within_budget:
        raise RuntimeError(f"perturbation {final.max_perturbation} exceeded epsilon {epsilon}")
    report = {**config, **extra, "attack_success_rate": final.result.success_rate,
              "attack_success_ci": list(final.result.success_ci), "episodes": final.result.episodes,
              "max_perturbation": final.max_perturbation, "mean_perturbation": final.mean_perturbation,
              "train_minutes_this_session": round((time.perf_counter() - started) / 60, 2)}
    (run.dir / "report.json").write_text(json.dumps(report, indent=1))
    return report


def _trained_attack(method, policy, victim, epsilon, norm, ppo: PPOConfig, seed):
    if method == "sa-rl":
        return sarl_attack(policy)
    return paad_attack(policy, victim, epsilon, norm, ppo.lam, ppo.actor_steps, seed)


def _train_ppo(method, run: Run, env, victim, target, reward, epsilon, norm, seed, cfg: PPOConfig, make_env,
               progress: bool):
    """PPO in the method's adversary MDP, with a checkpoint after every evaluation (resume: run again).

    Returns the policy and the number of PPO epochs (passes over a rollout, as SB3 counts updates) of this call.
    """
    from stable_baselines3.common.callbacks import BaseCallback

    from rat.attacks.rat import evaluate_attack

    if method == "sa-rl":
        mdp = StateAdversaryEnv(env, victim, reward, target, epsilon, norm)
    else:
        mdp = DirectorEnv(env, victim, reward, target, epsilon, norm, lam=cfg.lam, actor_steps=cfg.actor_steps)
    model = _ppo(mdp, cfg, seed)
    if run.has_checkpoint():
        state, ckpt_meta = load_checkpoint(run.checkpoint_path, "ppo-run")
        model.policy.load_state_dict(state["policy"])
        model.policy.optimizer.load_state_dict(state["optimizer"])
        model.num_timesteps = int(ckpt_meta["step"])
        run.logger.truncate_after(model.num_timesteps)

    from tqdm.auto import tqdm

    bar = tqdm(total=cfg.total_steps, initial=model.num_timesteps, desc=f"{method} {target.name}",
               disable=not progress)

    class Progress(BaseCallback):
        def __init__(self):
            super().__init__()
            self.next_eval = (model.num_timesteps // cfg.eval_every + 1) * cfg.eval_every
            self.episode_success, self.last = False, model.num_timesteps

        def _on_step(self) -> bool:
            info = self.locals["infos"][0]
            self.episode_success |= bool(info.get("target_success", False))
            if self.locals["dones"][0]:
                run.logger.log(self.num_timesteps, {"behaviour_success": float(self.episode_success)})
                self.episode_success = False
            bar.update(self.num_timesteps - self.last)
            self.last = self.num_timesteps
            return True

        def _on_rollout_end(self) -> None:
            if self.num_timesteps < self.next_eval:
                return
            self.next_eval += cfg.eval_every
            attack = _trained_attack(method, model.policy, victim, epsilon, norm, cfg, seed)
            res = evaluate_attack(victim, attack, make_env(seed + 7), target, epsilon, norm, cfg.eval_episodes,
                                  seed=10**7 + self.num_timesteps)
            run.logger.log(self.num_timesteps, {"eval_success_rate": res.result.success_rate})
            bar.set_postfix(attack_success=f"{res.result.success_rate:.0%}")
            save_checkpoint(run.checkpoint_path, "ppo-run", {"policy": model.policy.state_dict(),
                                                             "optimizer": model.policy.optimizer.state_dict()},
                            {"step": self.num_timesteps})

    remaining = cfg.total_steps - model.num_timesteps
    if remaining > 0:
        model.learn(remaining, callback=Progress(), reset_num_timesteps=False)
    bar.close()
    return model.policy, int(model._n_updates)  # epochs; target_kl may end a rollout's passes early


def load_attack(run: str | Path, victim: Victim | None = None) -> tuple[Callable[[np.ndarray], np.ndarray], dict]:
    """Any saved attack (RAT or a baseline) as ``obs -> Δ``, with its metadata.

    The gradient attacks (PA-AD, MAD) need the ``victim`` they attack.
    """
    from rat.attacks.rat import adversary_function, load_adversary

    path = Path(run)
    meta = read_meta(path / "adversary" if path.is_dir() else path)["meta"]
    method = meta.get("method", "rat")
    if method == "rat":
        adversary, meta = load_adversary(path)
        return adversary_function(adversary), {**meta, "method": "rat"}
    state, meta = load_checkpoint(path / "adversary" if path.is_dir() else path, "baseline-adversary")
    epsilon, norm, seed, dim = float(meta["epsilon"]), meta["norm"], int(meta["seed"]), int(meta["obs_dim"])
    if method in ("pa-ad", "mad") and victim is None:
        raise RatError(f"a {method} attack needs the victim it attacks")
    if method == "random":
        return random_attack(dim, norm, seed), meta
    if method == "mad":
        return mad_attack(victim, epsilon, norm, seed), meta
    cfg = PPOConfig(**meta["ppo"])
    obs_space = gym.spaces.Box(-np.inf, np.inf, (dim,), np.float64)
    act_dim = dim if method == "sa-rl" else int(meta["act_dim"])
    policy = _policy_network(obs_space, gym.spaces.Box(-1.0, 1.0, (act_dim,), np.float32), cfg)
    policy.load_state_dict(state["policy"])
    return _trained_attack(method, policy, victim, epsilon, norm, cfg, seed), meta


def ppo_preset(preset: str, steps: int | None = None, **overrides) -> PPOConfig:
    """PPO budgets by name: ``paper`` (table 6, 10⁶ steps) or ``cpu`` (this machine)."""
    if preset == "paper":
        return replace(PPOConfig(total_steps=steps or 1_000_000), **overrides)
    if preset == "cpu":
        # Departure for a CPU: table 6's learning rate (5e-5) and minibatch (32) need ~10⁶ steps;
        # with 5×10⁴ steps we take SB3's defaults for both.
        return replace(PPOConfig(total_steps=steps or 50_000, learning_rate=3e-4, batch_size=64), **overrides)
    raise RatError(f"unknown preset '{preset}'; use one of: cpu, paper")
