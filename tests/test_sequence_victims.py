"""Decision Transformer victims: hub-layout round trip, context over an episode, gradients, the threat model."""

import json

import numpy as np
import pytest
import torch

from rat.attacks import ThreatModel
from rat.errors import RatError

transformers = pytest.importorskip("transformers", reason="pip install 'rat[dt]' (the dev extra has it)")

from rat.victims.sequence import (  # noqa: E402
    DT_META,
    DecisionTransformerVictim,
    load_decision_transformer,
    save_decision_transformer,
)

OBS, ACT, K = 5, 3, 4


def tiny_model(seed=0):
    torch.manual_seed(seed)
    config = transformers.DecisionTransformerConfig(state_dim=OBS, act_dim=ACT, hidden_size=16, max_ep_len=50,
                                                    n_layer=1, n_head=1, n_positions=64, action_tanh=True)
    return transformers.DecisionTransformerModel(config).eval()


MEAN, STD = np.linspace(-1, 1, OBS), np.linspace(0.5, 2, OBS)


def reference_action(model, states, actions, rtg, timesteps):
    """The hub's own recipe (the Decision Transformer blog's get_action): pad on the left to K, mask, predict."""
    states = (torch.as_tensor(np.asarray(states), dtype=torch.float32) - torch.as_tensor(MEAN, dtype=torch.float32)) \
        / torch.as_tensor(STD, dtype=torch.float32)
    actions = torch.cat([torch.as_tensor(np.asarray(actions), dtype=torch.float32).reshape(-1, ACT), torch.zeros(1, ACT)])
    rtg = torch.as_tensor(np.asarray(rtg), dtype=torch.float32).reshape(-1, 1) / 1000.0
    timesteps = torch.as_tensor(np.asarray(timesteps)).reshape(-1)
    states, actions, rtg, timesteps = states[-K:], actions[-K:], rtg[-K:], timesteps[-K:]
    pad = K - len(states)
    mask = torch.cat([torch.zeros(pad), torch.ones(len(states))]).long().unsqueeze(0)
    z = lambda x, *shape: torch.cat([torch.zeros(pad, *shape, dtype=x.dtype), x]).unsqueeze(0)  # noqa: E731
    _, action_preds, _ = model(states=z(states, OBS), actions=z(actions, ACT), rewards=torch.zeros(1, K, 1),
                               returns_to_go=z(rtg, 1), timesteps=z(timesteps).long(), attention_mask=mask,
                               return_dict=False)
    return action_preds[0, -1]


@pytest.fixture
def saved(tmp_path):
    model = tiny_model()
    save_decision_transformer(tmp_path / "dt", model, MEAN, STD, target_return=3600.0, context_length=K,
                              task="HalfCheetah-v5")
    return model, tmp_path / "dt"


def test_a_checkpoint_in_the_hub_layout_loads_and_acts_as_the_hubs_recipe_over_an_episode(saved):
    model, directory = saved
    assert (directory / "config.json").exists() and (directory / "model.safetensors").exists()
    victim = load_decision_transformer(directory)
    assert victim.meta["task"] == "HalfCheetah-v5" and victim.context_length == K
    rng = np.random.default_rng(0)
    context, states, actions, rtg, timesteps = victim.initial_context(), [], [], [3600.0], [0]
    for t in range(9):  # longer than K: the context keeps the last K - 1 steps, the current one makes K
        obs = rng.normal(size=OBS)
        with torch.no_grad():
            action = victim.act(torch.as_tensor(obs).unsqueeze(0), context)[0]
        states.append(obs)
        torch.testing.assert_close(action, reference_action(model, states, actions, rtg, timesteps))
        reward = float(rng.normal())
        context = victim.update_context(context, torch.as_tensor(obs).unsqueeze(0), action.unsqueeze(0),
                                        torch.tensor([reward]))
        actions.append(action.numpy())
        rtg.append(rtg[-1] - reward)
        timesteps.append(t + 1)
        assert context.length == min(t + 1, K - 1) and int(context.timesteps[0, -1]) == t + 1
        torch.testing.assert_close(context.returns_to_go[0, -1], torch.tensor(rtg[-1]))
    fresh = victim.initial_context()  # reset: a new episode starts from the target return at step 0
    assert fresh.length == 0 and float(fresh.returns_to_go[0, -1]) == 3600.0 and int(fresh.timesteps[0, -1]) == 0


def test_gradients_reach_the_current_observation_and_nothing_in_the_victim_changes(saved):
    _, directory = saved
    victim = load_decision_transformer(directory)
    before = {k: v.clone() for k, v in victim.state_dict().items()}
    context = victim.initial_context()
    for _ in range(3):
        obs = torch.randn(1, OBS)
        context = victim.update_context(context, obs, victim.act(obs, context).detach(), torch.tensor([1.0]))
    threat = ThreatModel(0.1)
    obs = torch.randn(1, OBS)
    delta = torch.zeros(1, OBS, requires_grad=True)
    victim.act(threat.perturb(obs, delta), context).sum().backward()
    assert delta.grad is not None and delta.grad.abs().sum() > 0
    assert all(p.grad is None and not p.requires_grad for p in victim.parameters())
    assert all(torch.equal(before[k], v) for k, v in victim.state_dict().items())


def test_the_perturbed_states_stay_in_the_context_within_the_ball(saved):
    _, directory = saved
    victim, threat, rng = load_decision_transformer(directory), ThreatModel(0.1, "linf"), np.random.default_rng(1)
    context, true_states = victim.initial_context(), []
    for _ in range(6):
        obs = torch.as_tensor(rng.normal(size=(1, OBS)), dtype=torch.float32)
        seen = threat.perturb(obs, torch.as_tensor(rng.uniform(-3, 3, size=(1, OBS)), dtype=torch.float32))
        with torch.no_grad():
            context = victim.update_context(context, seen, victim.act(seen, context), torch.tensor([0.0]))
        true_states.append(obs[0])
    kept = torch.stack(true_states[-(K - 1):])
    gap = (context.states[0] - kept).abs().max(-1).values
    assert torch.all(gap <= 0.1 + 1e-6) and torch.all(gap > 0)  # what the victim saw, within ε of the truth


def test_a_pytorch_bin_loads_only_as_tensors_and_bad_directories_are_one_line(saved, tmp_path):
    model, directory = saved
    (directory / "model.safetensors").unlink()
    torch.save(model.state_dict(), directory / "pytorch_model.bin")
    victim = load_decision_transformer(directory)
    obs = torch.randn(1, OBS)
    with torch.no_grad():
        torch.testing.assert_close(victim.act(obs)[0], reference_action(model, [obs[0].numpy()], [], [3600.0], [0]))

    class Code:
        def __reduce__(self):
            return (print, ("ran code from a model file",))

    torch.save({"w": Code()}, directory / "pytorch_model.bin")
    with pytest.raises(RatError, match="holds more than tensors"):
        load_decision_transformer(directory)
    (directory / DT_META).unlink()
    with pytest.raises(RatError, match="lacks rat_dt.json"):
        load_decision_transformer(directory)
    with pytest.raises(RatError, match="no Decision Transformer at"):
        load_decision_transformer(tmp_path / "nowhere")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "config.json").write_text(json.dumps({"model_type": "gpt2"}))
    (tmp_path / "other" / DT_META).write_text("{}")
    with pytest.raises(RatError, match="not a Decision Transformer|not readable"):
        load_decision_transformer(tmp_path / "other")


def test_the_split_forward_gives_the_models_actions_and_gradients_and_a_model_it_cannot_match_runs_whole():
    torch.manual_seed(2)  # two layers, two heads, the layer-scaled attention variant
    config = transformers.DecisionTransformerConfig(state_dim=OBS, act_dim=ACT, hidden_size=16, max_ep_len=50, n_layer=2,
                                                    n_head=2, n_positions=64, action_tanh=True,
                                                    scale_attn_by_inverse_layer_idx=True)
    spaces = (gym_box(OBS), gym_box(ACT, 1.0))

    def trained_like():  # attention as peaked as a trained model's (at initialisation it is nearly uniform)
        model = transformers.DecisionTransformerModel(config)
        with torch.no_grad():
            for block in model.encoder.h:
                block.attn.c_attn.weight.mul_(10.0)
        return model

    victim = DecisionTransformerVictim(trained_like(), *spaces, MEAN, STD, 100.0, context_length=K)
    assert victim.split_forward  # the self-check at construction passed
    context, rng = victim.initial_context(6), np.random.default_rng(4)
    for _ in range(2):  # a young context: part of it is padding
        obs = torch.as_tensor(rng.normal(size=(6, OBS)), dtype=torch.float32)
        context = victim.update_context(context, obs, victim.act(obs, context).detach(), torch.ones(6))
    obs = torch.tensor(rng.normal(size=(6, OBS)), dtype=torch.float32, requires_grad=True)
    derivatives = []
    for split in (True, False):
        victim.split_forward = split
        action = victim.act(obs, context)
        (grad,) = torch.autograd.grad(action.pow(2).sum(), obs, create_graph=True)
        (second,) = torch.autograd.grad(grad.pow(2).sum(), obs)  # the weighting network's hypergradient needs it
        derivatives.append((action, grad, second))
    for split, whole in zip(*derivatives):
        torch.testing.assert_close(split, whole, atol=1e-5, rtol=1e-4)
    assert derivatives[0][1].abs().sum() > 0

    class Misread(DecisionTransformerVictim):  # a split forward that gets the attention scale wrong
        def _attention_scale(self, layer, head_dim):
            return 1.0

    misread = Misread(trained_like(), *spaces, MEAN, STD, 100.0, context_length=K)
    assert not misread.split_forward  # the check caught it: the whole model runs, and acts as the model does
    inputs = misread._inputs(obs.detach(), context)
    with torch.no_grad():
        torch.testing.assert_close(misread.act(obs.detach(), context), misread._model_action(*inputs).clamp(-1, 1))
        assert not torch.allclose(misread._split_action(*inputs), misread._model_action(*inputs), atol=1e-4)


def test_a_prepared_context_acts_as_the_context_and_a_model_the_split_cannot_match_keeps_it_whole(saved):
    """An attacker refining Δ acts many times in one context; prepared, its past runs once, with the same actions."""
    from rat.victims.sequence import PreparedContext

    _, directory = saved
    victim = load_decision_transformer(directory)
    rng = np.random.default_rng(5)
    for steps in (0, 2, 7):  # a fresh episode, a young one, one past K
        context = victim.initial_context(2)
        for _ in range(steps):
            obs = torch.as_tensor(rng.normal(size=(2, OBS)), dtype=torch.float32)
            context = victim.update_context(context, obs, victim.act(obs, context).detach(), torch.ones(2))
        prepared = victim.prepare(context)
        assert isinstance(prepared, PreparedContext)
        obs = torch.tensor(rng.normal(size=(2, OBS)), dtype=torch.float32, requires_grad=True)
        for each in (context, prepared):
            action = victim.act(obs, each)
            (grad,) = torch.autograd.grad(action.pow(2).sum(), obs)
            if each is context:
                expected = action, grad
        torch.testing.assert_close((action, grad), expected, atol=1e-5, rtol=1e-4)
        assert grad.abs().sum() > 0
        first = victim.unpack_context(victim.pack_context(context)[:1])  # one episode's, for several observations
        with torch.no_grad():
            torch.testing.assert_close(victim.act(obs, victim.prepare(first)), victim.act(obs, first),
                                       atol=1e-5, rtol=1e-4)
    victim.split_forward = False  # as for a model whose blocks the split does not reproduce
    assert victim.prepare(context) is context


def gym_box(size, bound=np.inf):
    import gymnasium as gym

    return gym.spaces.Box(-bound, bound, (size,), np.float32)


def test_a_batch_of_observations_shares_one_episodes_context(saved):
    _, directory = saved
    victim = load_decision_transformer(directory)
    assert isinstance(victim, DecisionTransformerVictim)
    context = victim.initial_context()
    obs = torch.randn(1, OBS)
    context = victim.update_context(context, obs, victim.act(obs, context).detach(), torch.tensor([2.0]))
    batch = torch.randn(7, OBS)
    with torch.no_grad():
        together = victim.act(batch, context)
        alone = torch.cat([victim.act(b.unsqueeze(0), context) for b in batch])
    torch.testing.assert_close(together, alone)


def test_contexts_of_different_episodes_stack_into_one_batch_and_pack_into_rows(saved):
    _, directory = saved
    victim = load_decision_transformer(directory)
    contexts, observations, rng = [], [], np.random.default_rng(3)
    for steps in (0, 2, 7):  # a fresh episode, a young one, one past K
        context = victim.initial_context()
        for _ in range(steps):
            obs = torch.as_tensor(rng.normal(size=(1, OBS)), dtype=torch.float32)
            context = victim.update_context(context, obs, victim.act(obs, context).detach(), torch.tensor([rng.normal()]))
        contexts.append(context)
        observations.append(torch.as_tensor(rng.normal(size=(1, OBS)), dtype=torch.float32))
    packed = torch.cat([victim.pack_context(c) for c in contexts])
    assert packed.shape == (3, victim.context_size)
    batch = victim.unpack_context(packed)
    assert [victim.unpack_context(packed[i:i + 1]).length for i in range(3)] == [0, 2, K - 1]
    with torch.no_grad():
        together = victim.act(torch.cat(observations), batch)
        alone = torch.cat([victim.act(o, c) for o, c in zip(observations, contexts)])
    torch.testing.assert_close(together, alone)


def test_an_evaluation_keeps_the_victims_context_and_an_attacked_one_stays_in_the_budget(tmp_path):
    import gymnasium as gym

    from rat.attacks import evaluate_attack
    from rat.envs import get_target, make_task
    from rat.eval import evaluate
    from rat.victims.base import numpy_policy

    torch.manual_seed(0)
    config = transformers.DecisionTransformerConfig(state_dim=17, act_dim=6, hidden_size=16, max_ep_len=100,
                                                    n_layer=1, n_head=1, n_positions=64)
    save_decision_transformer(tmp_path / "dt", transformers.DecisionTransformerModel(config), np.zeros(17),
                              np.ones(17), target_return=500.0, context_length=K, task="HalfCheetah-v5")
    victim = load_decision_transformer(tmp_path / "dt")
    env = gym.wrappers.TimeLimit(make_task("HalfCheetah-v5"), 12)
    policy = numpy_policy(victim)
    result = evaluate(policy, env, 2, seed=5)
    # the same episode by hand: act on what is seen, record the step, lower the return-to-go
    obs, _ = env.reset(seed=6)
    context, total = victim.initial_context(), 0.0
    for _ in range(12):
        o = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
        with torch.no_grad():
            action = victim.act(o, context)
        obs, reward, _, _, _ = env.step(action[0].numpy())
        context = victim.update_context(context, o, action, torch.tensor([reward]))
        total += reward
    assert policy.context.length == K - 1 and int(policy.context.timesteps[0, -1]) == 12
    torch.testing.assert_close(policy.context.states, context.states)
    assert np.isclose(policy.context.returns_to_go[0, -1].item(), 500.0 - total, atol=1e-3)
    assert result.episodes == 2
    attacked = evaluate_attack(victim, lambda o: np.ones_like(o), env, get_target("cheetah-backward"),
                               ThreatModel(0.1), 1, seed=6)
    assert attacked.within_budget and attacked.max_perturbation > 0.099


def test_sa_rl_s_mdp_keeps_the_victims_context_and_history_blind_attacks_refuse_a_sequence_victim(saved):
    import gymnasium as gym

    from rat.attacks.rl import DirectorEnv, StateAdversaryEnv
    from rat.attacks.simple import mad_attack
    from rat.envs.targets import TargetBehaviour

    _, directory = saved
    victim = load_decision_transformer(directory)

    class Walk(gym.Env):  # OBS-dimensional states, ACT-dimensional actions, reward 1 a step
        observation_space = gym.spaces.Box(-np.inf, np.inf, (OBS,), np.float64)
        action_space = gym.spaces.Box(-1.0, 1.0, (ACT,), np.float32)

        def reset(self, *, seed=None, options=None):
            self.x = np.random.default_rng(seed).normal(size=OBS)
            return self.x.copy(), {}

        def step(self, action):
            self.x = self.x + 0.1 * np.resize(action, OBS)
            return self.x.copy(), 1.0, False, False, {"success": False}

    target = TargetBehaviour("any", "nothing", lambda o, a, n, i: 0.0, lambda i: False)
    mdp, threat = StateAdversaryEnv(Walk(), victim, target.reward, target, ThreatModel(0.1)), ThreatModel(0.1)
    obs, _ = mdp.reset(seed=0)
    true_states = []
    for t in range(6):
        true_states.append(obs)
        obs, *_, info = mdp.step(np.ones(OBS, np.float32))
        context = mdp.policy.context
        assert context.length == min(t + 1, K - 1) and float(context.returns_to_go[0, -1]) == 3600.0 - (t + 1)
        np.testing.assert_allclose(context.states[0, -1].numpy(), true_states[-1] + info["perturbation"], atol=1e-5)
    mdp.reset(seed=1)
    assert mdp.policy.context.length == 0  # a new episode, a fresh history
    for make in (lambda: DirectorEnv(Walk(), victim, target.reward, target, threat),
                 lambda: mad_attack(victim, threat, seed=0)):
        with pytest.raises(RatError, match="without the victim's history.*use rat, random or sa-rl"):
            make()
