"""The RL baselines of the paper's table 1: SA-RL and PA-AD, learning with PPO.

- ``sa-rl`` (Zhang et al. 2021): an RL adversary in the state-adversarial MDP of the paper's
  lemma 3.1, :class:`StateAdversaryEnv`: its action is the perturbation, the frozen victim acts
  on the perturbed observation, the reward is the target reward of the victim's transition.
- ``pa-ad`` (Sun et al. 2022): an RL *director* in :class:`DirectorEnv` chooses a direction in
  the victim's action space; the actor (:func:`rat.attacks.gradient.directed_perturbation`)
  finds the perturbation that moves the victim's action that way.

Both learn with Stable-Baselines3's PPO at the paper's table 6 settings (:class:`PPOConfig`),
from the true target reward (``reward="oracle"``) or from r̂ learned offline from exactly the
labels of a label store (``reward="labels"``: the labels of the RAT run they are compared
with; :mod:`rat.preferences.offline`). Both adversary MDPs are plain gymnasium environments, so
any other PPO can train them too.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from rat import seeds
from rat.attacks.base import AttackSetup, register_attack
from rat.attacks.evaluation import evaluate_attack
from rat.attacks.gradient import directed_perturbation
from rat.attacks.runs import baseline_run
from rat.attacks.threat import Perturbation, ThreatModel
from rat.envs.targets import RewardFn, TargetBehaviour
from rat.errors import RatError
from rat.loop import TrainingLoop
from rat.preferences.offline import learn_reward, reward_source, run_reward
from rat.preferences.reward_model import RewardModelConfig
from rat.reports import AttackReport
from rat.runs import Run
from rat.victims.base import Victim, VictimPolicy, check_compatible, require_memoryless

# --- the adversary MDPs ---------------------------------------------------------------------------------


class _AdversaryMDP(gym.Env):
    """The environment seen by an RL adversary: observation = true state, the victim acts on s̃.

    A sequence victim keeps its context over the episode (the states as perturbed), as in an evaluation.
    """

    metadata = {"render_modes": []}

    def __init__(self, env: gym.Env, victim: Victim, reward: RewardFn, target: TargetBehaviour, threat: ThreatModel):
        check_compatible(victim, env)
        self.env, self.victim, self.reward, self.target, self.threat = env, victim, reward, target, threat
        self.policy = VictimPolicy(victim)
        self.observation_space = env.observation_space
        self._obs: np.ndarray | None = None

    def perturbation(self, obs: torch.Tensor, action: np.ndarray) -> torch.Tensor:
        """Δ in the unit ball for the adversary's ``action`` at the true observation ``obs [1, d]``."""
        raise NotImplementedError

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._obs, info = self.env.reset(seed=seed, options=options)
        self._success = self.target.episode_success()
        self.policy.reset()
        return self._obs, info

    def step(self, action: np.ndarray):
        s = torch.as_tensor(self._obs, dtype=torch.float32).unsqueeze(0)
        delta = self.perturbation(s, np.asarray(action, np.float32))
        victim_action = self.policy(self.threat.perturb(s, delta).squeeze(0).detach().numpy())
        next_obs, env_reward, terminated, truncated, info = self.env.step(victim_action)
        self.policy.observe(env_reward)
        reward = self.reward(self._obs, victim_action, next_obs, info)
        info = dict(info, victim_action=victim_action, target_success=self._success(info),
                    perturbation=(self.threat.epsilon * delta.squeeze(0)).numpy())
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
        return self.threat.project(torch.as_tensor(action, dtype=torch.float32).unsqueeze(0))


class DirectorEnv(_AdversaryMDP):
    """PA-AD's director MDP: action d ∈ [−1, 1]^|A| (a direction in the victim's action space).

    The actor turns d into the perturbation maximising cos(μ(s̃) − μ(s), d) + λ‖μ(s̃) − μ(s)‖
    by ``actor_steps`` gradient steps from a random start (1: the paper's FGSM).
    """

    def __init__(self, *args, lam: float = 1.0, actor_steps: int = 1, **kwargs):
        super().__init__(*args, **kwargs)
        require_memoryless(self.victim, "pa-ad")
        self.lam, self.actor_steps = lam, actor_steps
        self.action_space = gym.spaces.Box(-1.0, 1.0, self.env.action_space.shape, np.float32)

    def perturbation(self, obs, action):
        direction = torch.as_tensor(action, dtype=torch.float32).unsqueeze(0)
        return directed_perturbation(self.victim, obs, direction, self.threat, self.lam, self.actor_steps,
                                     self.np_random)  # random starts follow reset(seed=...)


# --- PPO ----------------------------------------------------------------------------------------------------


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
    device: str = "cpu"  #: auto, cpu or cuda; Stable-Baselines3 runs MLP policies fastest on the CPU

    def __post_init__(self):
        for name in ("total_steps", "batch_size", "n_steps", "n_epochs", "hidden", "layers", "actor_steps",
                     "eval_every", "eval_episodes", "final_eval_episodes"):
            if getattr(self, name) <= 0:
                raise RatError(f"{name.replace('_', '-')} must be positive, got {getattr(self, name)}")
        if not self.learning_rate > 0:
            raise RatError(f"learning-rate must be positive, got {self.learning_rate}")
        if self.total_steps < self.n_steps:
            raise RatError(f"{self.total_steps} steps end before PPO's first update (after a rollout of "
                           f"n_steps={self.n_steps}); give --steps >= {self.n_steps} or --preset smoke")


def _policy_kwargs(cfg: PPOConfig) -> dict:
    arch = [cfg.hidden] * cfg.layers
    return {"net_arch": {"pi": arch, "vf": arch}, "activation_fn": torch.nn.Tanh}


def _ppo(env: gym.Env, cfg: PPOConfig, seed: int):
    from stable_baselines3 import PPO

    from rat.device import resolve_device

    return PPO("MlpPolicy", env, learning_rate=cfg.learning_rate, n_steps=cfg.n_steps, batch_size=cfg.batch_size,
               n_epochs=cfg.n_epochs, gamma=cfg.gamma, gae_lambda=cfg.gae_lambda, clip_range=cfg.clip_range,
               ent_coef=cfg.ent_coef, target_kl=cfg.target_kl, policy_kwargs=_policy_kwargs(cfg), seed=seed,
               device=resolve_device(cfg.device), verbose=0)


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


# --- attacks as functions obs -> Δ -----------------------------------------------------------------------


def sarl_perturbation(policy) -> Perturbation:
    act = ppo_direction(policy)
    return lambda obs: act(obs).astype(np.float64)


def paad_perturbation(policy, victim: Victim, threat: ThreatModel, lam: float, steps: int, seed: int) -> Perturbation:
    require_memoryless(victim, "pa-ad")
    rng, direct = np.random.default_rng(seed), ppo_direction(policy)

    def delta(obs: np.ndarray) -> np.ndarray:
        s = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
        d = torch.as_tensor(direct(obs), dtype=torch.float32).unsqueeze(0)
        return directed_perturbation(victim, s, d, threat, lam, steps, rng).squeeze(0).double().numpy()

    return delta


# --- training -----------------------------------------------------------------------------------------------


class PPOTrainer:
    """A PPO adversary in its MDP: the state a :class:`~rat.loop.TrainingLoop` checkpoints and evaluates.

    Stable-Baselines3's ``learn`` drives the steps; its callbacks hand the loop each episode's
    result and every rollout's end (where evaluations and checkpoints happen).
    """

    kind = "ppo-run"

    def __init__(self, attack: PPOAttack, setup: AttackSetup, mdp: gym.Env, cfg: PPOConfig):
        self.attack, self.setup, self.cfg, self.finished = attack, setup, cfg, False
        self.model = _ppo(mdp, cfg, setup.seed)

    @property
    def step(self) -> int:
        return self.model.num_timesteps

    def perturbation(self) -> Perturbation:
        return self.attack.perturbation(self.model.policy, self.setup.victim, self.setup.threat, self.cfg,
                                        self.setup.seed)

    def evaluate(self) -> dict[str, float]:
        s = self.setup
        res = evaluate_attack(s.victim, self.perturbation(), s.make_env(s.seed + seeds.EVAL_ENV), s.target, s.threat,
                              self.cfg.eval_episodes, seeds.periodic(self.step))
        return {"eval_success_rate": res.result.success_rate}

    def state_dict(self) -> dict:
        return {"policy": self.model.policy.state_dict(), "optimizer": self.model.policy.optimizer.state_dict()}

    def load_state_dict(self, state: dict, meta: dict) -> None:
        self.model.policy.load_state_dict(state["policy"])
        self.model.policy.optimizer.load_state_dict(state["optimizer"])
        self.model.num_timesteps = int(meta["step"])

    def checkpoint_meta(self) -> dict:
        return {}

    def rollout(self) -> int:
        """One more rollout of ``n_steps`` and PPO's update on it, continuing the episode under way (a
        robust-training loop steps the adversary this way between its agent's phases); returns the steps taken."""
        before = self.step
        self.model.learn(self.cfg.n_steps, reset_num_timesteps=False)
        return self.step - before

    def learn(self, loop: TrainingLoop) -> int:
        """PPO until the loop's total; returns the PPO epochs of this call (passes over a rollout, as SB3 counts)."""
        from stable_baselines3.common.callbacks import BaseCallback

        class Hooks(BaseCallback):
            def __init__(self):
                super().__init__()
                self.succeeded = False

            def _on_step(self) -> bool:
                self.succeeded |= bool(self.locals["infos"][0].get("target_success", False))
                if self.locals["dones"][0]:
                    loop.log(self.num_timesteps, {"behaviour_success": float(self.succeeded)})
                    self.succeeded = False
                return True

            def _on_rollout_end(self) -> None:
                loop.after(self.num_timesteps, boundary=True)

        loop.open()
        remaining = loop.total - self.step
        if remaining > 0:
            self.model.learn(remaining, callback=Hooks(), reset_num_timesteps=False)
        loop.close()
        return int(self.model._n_updates)  # epochs; target_kl may end a rollout's passes early


class PPOAttack:
    """What SA-RL and PA-AD share: PPO in an adversary MDP, on the true or the learned target reward."""

    method = ""

    def mdp(self, env: gym.Env, setup: AttackSetup, reward: RewardFn, cfg: PPOConfig) -> gym.Env:
        raise NotImplementedError

    def perturbation(self, policy, victim: Victim, threat: ThreatModel, cfg: PPOConfig, seed: int) -> Perturbation:
        raise NotImplementedError

    def action_dim(self, meta: dict) -> int:
        raise NotImplementedError

    def train(self, setup: AttackSetup, config: PPOConfig, out: Path,
              reward_config: RewardModelConfig = RewardModelConfig()) -> AttackReport:
        if setup.reward == "labels" and setup.labels is None:
            raise RatError(f"{self.name} learns from preference labels: give --labels STORE (e.g. a RAT run's "
                           "labels.sqlite, or the run itself), or --reward oracle for the true target reward")

        def prepare(env):  # r̂ from the label store or the RAT run, before the run directory exists
            if setup.reward != "labels":
                return None, {}
            obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
            if setup.labels.is_dir():  # a finished RAT run: the r̂ it ended with
                return run_reward(setup.labels, obs_dim, act_dim)
            return learn_reward(setup.labels, obs_dim, act_dim, reward_config, setup.seed, cache=True)

        def train(run: Run, env: gym.Env, prepared) -> tuple[dict, dict]:
            ensemble, reward_metrics = prepared
            details = {k: v for k, v in reward_metrics.items() if k != "label_ids"}
            if ensemble is not None:
                (run.dir / "labels_used.json").write_text(__import__("json").dumps(reward_metrics["label_ids"]))
            trainer = PPOTrainer(self, setup, self.mdp(env, setup, reward_source(setup.target, ensemble), config),
                                 config)
            loop = TrainingLoop(run, trainer, config.total_steps, eval_every=config.eval_every,
                                checkpoint_every=config.eval_every, desc=f"{self.name} {setup.target.name}",
                                progress=setup.progress)
            loop.resume()
            details["ppo_updates"] = trainer.learn(loop)
            details["train_minutes"] = loop.total_seconds / 60
            details["steps"] = trainer.step
            return {"policy": trainer.model.policy.state_dict()}, details

        return baseline_run(self.name, setup, out, {"ppo": config}, train, prepare,
                            config.final_eval_episodes)

    def load(self, run: Path, meta: dict, victim: Victim) -> Perturbation:
        from rat.checkpoint import load_checkpoint

        cfg = PPOConfig(**meta["ppo"])
        dim = int(meta["obs_dim"])
        obs_space = gym.spaces.Box(-np.inf, np.inf, (dim,), np.float64)
        policy = _policy_network(obs_space, gym.spaces.Box(-1.0, 1.0, (self.action_dim(meta),), np.float32), cfg)
        state, _ = load_checkpoint(Path(run) / "adversary", "baseline-adversary")
        policy.load_state_dict(state["policy"])
        return self.perturbation(policy, victim, ThreatModel(float(meta["epsilon"]), meta["norm"]), cfg,
                                 int(meta["seed"]))


@register_attack("sa-rl", config=PPOConfig, rewards=("labels", "oracle"))
class SARL(PPOAttack):
    """SA-RL: PPO in the state-adversarial MDP; its action is the perturbation (Zhang et al. 2021)."""

    def mdp(self, env, setup, reward, cfg):
        return StateAdversaryEnv(env, setup.victim, reward, setup.target, setup.threat)

    def perturbation(self, policy, victim, threat, cfg, seed):
        return sarl_perturbation(policy)

    def action_dim(self, meta):
        return int(meta["obs_dim"])


@register_attack("pa-ad", config=PPOConfig, rewards=("labels", "oracle"))
class PAAD(PPOAttack):
    """PA-AD: a PPO director picks a direction in the victim's action space, a gradient actor follows it (Sun et al. 2022)."""

    def mdp(self, env, setup, reward, cfg):
        return DirectorEnv(env, setup.victim, reward, setup.target, setup.threat, lam=cfg.lam,
                           actor_steps=cfg.actor_steps)

    def perturbation(self, policy, victim, threat, cfg, seed):
        if victim is None:
            raise RatError("a pa-ad attack needs the victim it attacks")
        return paad_perturbation(policy, victim, threat, cfg.lam, cfg.actor_steps, seed)

    def action_dim(self, meta):
        return int(meta["act_dim"])
