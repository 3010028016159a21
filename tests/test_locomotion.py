"""Locomotion tasks (Gymnasium MuJoCo) and their target behaviours' success tests on hand-made transitions."""

import numpy as np
import pytest

from rat.envs import get_target, make_task
from rat.errors import RatError


def cheetah(x=0.0, start=0.0, pitch=0.0, vx=0.0):
    return {"x_position": x, "start_x_position": start, "torso_pitch": pitch, "x_velocity": vx, "torso_z": 0.6}


def walker(z=1.2, right=0.0, left=0.0, thigh=0.0, thigh_left=0.0, vx=0.0):
    return {"torso_z": z, "foot_z": right, "foot_left_z": left, "thigh_angle": thigh, "thigh_left_angle": thigh_left,
            "x_velocity": vx}


def held(target, infos):
    test = get_target(target).episode_success()
    return [test(info) for info in infos]


@pytest.mark.parametrize("task", ["HalfCheetah-v5", "Walker2d-v5"])
def test_locomotion_tasks_report_the_pose_the_targets_read(task):
    env = make_task(task, seed=3)
    obs, info = env.reset()
    assert obs.shape == (17,) and env.action_space.shape == (6,)
    again, _ = make_task(task, seed=3).reset()
    np.testing.assert_array_equal(obs, again)  # the seed fixes the first reset
    for _ in range(5):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    keys = {"x_position", "prev_x_position", "start_x_position", "torso_z", "torso_pitch", "task_reward"}
    if task == "Walker2d-v5":
        keys |= {"foot_z", "foot_left_z", "thigh_angle", "thigh_left_angle"}
    assert keys <= set(info) and info["task_reward"] == reward
    assert info["prev_x_position"] != info["x_position"] or info["x_velocity"] == 0


def test_cheetah_targets():
    backward = get_target("cheetah-backward")
    assert backward.success(cheetah(x=-2.5, start=0.5)) and not backward.success(cheetah(x=-2.4, start=0.5))
    assert backward.reward(None, None, None, cheetah(vx=-2.0)) == 2.0
    assert held("cheetah-pushup", [cheetah(pitch=1.5)] * 20)[-1]  # nose down, near vertical, 20 steps
    assert held("cheetah-pushup", [cheetah(pitch=-1.4)] * 20)[-1]
    assert not any(held("cheetah-pushup", [cheetah(pitch=1.5)] * 19 + [cheetah(pitch=0.5)]))
    assert not any(held("cheetah-pushup", [cheetah(pitch=0.9)] * 30))  # 52°: not a push-up


def test_walker_targets():
    assert held("walker-one-foot", [walker(right=0.2, left=0.02)] * 20)[-1]
    assert held("walker-one-foot", [walker(right=0.0, left=0.3)] * 20)[-1]
    assert not any(held("walker-one-foot", [walker(right=0.2, left=0.2)] * 30))  # both up: jumping
    assert not any(held("walker-one-foot", [walker(z=0.7, right=0.2)] * 30))  # fallen
    assert not any(held("walker-one-foot", [walker(right=0.2, vx=1.2)] * 40))  # a walking gait's swing phase
    one_foot = get_target("walker-one-foot").reward
    assert one_foot(None, None, None, walker(right=0.2)) > one_foot(None, None, None, walker(right=0.2, vx=1.0))
    assert held("walker-leg-raised", [walker(right=0.4, thigh=-0.9)] * 100)[-1]
    assert not any(held("walker-leg-raised", [walker(right=0.4, thigh=-0.9)] * 99))  # a long swing is not a dance
    assert not any(held("walker-leg-raised", [walker(right=0.4, thigh=-0.3)] * 30))  # foot high, leg not forward
    assert not any(held("walker-leg-raised", [walker(right=0.2, thigh=-0.9)] * 30))  # leg forward, foot low


def test_a_locomotion_target_refuses_another_robot():
    assert get_target("cheetah-pushup").env_task("HalfCheetah-v5") == "HalfCheetah-v5"
    with pytest.raises(RatError, match="for HalfCheetah-v5 victims, not 'Walker2d-v5'"):
        get_target("cheetah-pushup").env_task("Walker2d-v5")
    with pytest.raises(RatError, match="for Walker2d-v5 victims"):
        get_target("walker-one-foot").env_task("drawer-open-v3")


def test_an_attack_switches_within_each_tasks_own_episode_length():
    from rat.envs import make_task
    from rat.envs.tasks import episode_length

    assert episode_length(make_task("HalfCheetah-v5")) == 1000 and episode_length(make_task("Walker2d-v5")) == 1000
    assert episode_length(make_task("drawer-open-v3")) == 500


def test_videos_of_the_cheetah_follow_it_when_it_runs_off():
    """The free camera of gymnasium's default loses a running cheetah; ours tracks its body."""

    def body_pixels(frame):  # the cheetah is orange; floor and sky are not
        f = frame.astype(int)
        return int(((f[..., 0] > f[..., 1] + 40) & (f[..., 0] > f[..., 2] + 40)).sum())

    env = make_task("HalfCheetah-v5", render_mode="rgb_array")
    env.reset(seed=0)
    assert body_pixels(env.render()) > 500
    sim = env.unwrapped
    qpos = sim.data.qpos.copy()
    qpos[0] += 20.0  # 20 m down the track
    sim.set_state(qpos, sim.data.qvel)
    assert body_pixels(env.render()) > 500
    env.close()
