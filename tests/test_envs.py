import numpy as np
import pytest

from rat.envs import HORIZON, PAPER_TASKS, make_task
from rat.errors import RatError


def rollout(env, seed, steps=20):
    obs, info = env.reset(seed=seed)
    actions = np.random.default_rng(1).uniform(-1, 1, (steps, 4))
    trace = [obs]
    for a in actions:
        obs, *_ = env.step(a)
        trace.append(obs)
    return np.array(trace), info


def test_same_seed_gives_the_same_episode():
    a, _ = rollout(make_task("drawer-open-v3", seed=5), seed=11)
    b, _ = rollout(make_task("drawer-open-v3", seed=99), seed=11)
    np.testing.assert_allclose(a, b)


def test_different_seeds_give_different_episodes():
    a, _ = rollout(make_task("drawer-open-v3"), seed=1)
    b, _ = rollout(make_task("drawer-open-v3"), seed=2)
    assert not np.allclose(a[0], b[0])


@pytest.mark.parametrize("task", sorted(PAPER_TASKS))
def test_every_reset_redraws_object_and_goal(task):
    env = make_task(task, seed=0)
    goals, objects = [], []
    for _ in range(4):
        obs, info = env.reset()
        goals.append(info["goal_pos"])
        objects.append(info["obj_pos"])
        np.testing.assert_allclose(obs[36:39], info["goal_pos"])  # the goal is observed
    assert len({tuple(np.round(g, 6)) for g in goals}) > 1 or len({tuple(np.round(o, 6)) for o in objects}) > 1


def test_info_reports_positions_success_and_task_reward():
    env = make_task("drawer-close-v3")
    obs, info = env.reset(seed=0)
    for key in ("tcp_pos", "prev_tcp_pos", "tcp_init", "obj_pos", "goal_pos", "success", "task_reward"):
        assert key in info
    before = info["tcp_pos"]
    obs, reward, terminated, truncated, info = env.step(np.array([0.0, 0.0, 1.0, 0.0]))
    np.testing.assert_allclose(info["prev_tcp_pos"], before)
    assert info["tcp_pos"][2] > before[2]  # moved up
    assert info["task_reward"] == reward
    assert isinstance(info["success"], bool)
    # the tool centre point sits a few centimetres below the hand position that is observed
    assert 0.02 < obs[2] - info["tcp_pos"][2] < 0.07


def test_horizon_is_500_steps_and_truncates():
    env = make_task("window-open-v3")
    env.reset(seed=0)
    for t in range(1, HORIZON + 1):  # noqa: B007 (the count is read after the loop)
        _, _, terminated, truncated, _ = env.step(np.zeros(4))
        assert not terminated
        if truncated:
            break
    assert t == HORIZON and truncated


def test_unknown_task_names_the_fix():
    with pytest.raises(RatError, match="did you mean 'drawer-open-v3'.*rat list tasks"):
        make_task("drawer-opn-v3")


@pytest.mark.slow
@pytest.mark.parametrize("task, state_size, shadow_map", [("drawer-open-v3", 28, 1024), ("Walker2d-v5", 19, 2048)])
def test_recorded_physics_states_film_again_to_the_pixel_in_another_instance(task, state_size, shadow_map):
    """What the labelling page shows: frames rendered from recorded states and scene, in an environment
    whose own reset put the object and goal elsewhere, equal the recording environment's frames."""
    from rat.envs.physics import _model_data, physics_of, render_states, set_physics_state

    recorder, other = (make_task(task, seed=s, render_mode="rgb_array") for s in (3, 9))
    # a shadow map 4x the frame's side (224, 480 pixels), not MuJoCo's 4,096: half the time of a frame on a CPU
    assert _model_data(recorder)[0].vis.quality.shadowsize == shadow_map
    recorder.reset(seed=3)
    other.reset(seed=9)
    states, scene = [], None
    for _ in range(8):
        state, scene = physics_of(recorder)
        states.append(state)
        recorder.step(recorder.action_space.sample())
    assert states[0].shape == (state_size,)
    frames = render_states(recorder, np.stack(states))
    assert all(np.array_equal(a, b) for a, b in zip(render_states(other, np.stack(states), scene), frames))
    if task.startswith("drawer"):  # Meta-World moves object and goal in the model: without the scene, frames differ
        fresh = make_task(task, seed=9, render_mode="rgb_array")
        fresh.reset(seed=9)
        assert not np.array_equal(render_states(fresh, np.stack(states))[0], frames[0])
        fresh.close()
    with pytest.raises(RatError, match="does not fit this scene"):
        set_physics_state(other, np.zeros(3))
    recorder.close()
    other.close()
