import numpy as np
import pytest

from rat.envs import REACH_GOAL, get_target, list_targets, make_task, opposite_task, register_target
from rat.envs.targets import _REGISTRY
from rat.errors import RatError


def info_at(tcp, prev=None, init=None, **extra):
    tcp = np.asarray(tcp, float)
    return {"tcp_pos": tcp, "prev_tcp_pos": np.asarray(prev if prev is not None else tcp, float),
            "tcp_init": np.asarray(init if init is not None else tcp, float), **extra}


def reward(target, info):
    z = np.zeros(39)
    return target.reward(z, np.zeros(4), z, info)


def test_reach_success_is_five_centimetres_from_the_goal():
    reach = get_target("reach")
    assert reach.success(info_at(REACH_GOAL + [0.0, 0.0, 0.049]))
    assert not reach.success(info_at(REACH_GOAL + [0.0, 0.0, 0.051]))
    assert not reach.success(info_at([0.0, 0.6, 0.2]))


def test_reach_reward_is_ten_times_progress_far_from_the_goal():
    reach = get_target("reach")
    prev = REACH_GOAL + [0.0, -0.5, 0.0]
    now = REACH_GOAL + [0.0, -0.4, 0.0]
    assert reward(reach, info_at(now, prev)) == pytest.approx(10 * 0.1)
    assert reward(reach, info_at(prev, now)) == pytest.approx(-10 * 0.1)


def test_reach_reward_adds_the_tolerance_bonus_within_ten_centimetres():
    from metaworld.utils.reward_utils import tolerance

    reach = get_target("reach")
    init = REACH_GOAL + [0.0, -0.3, 0.0]
    now = REACH_GOAL + [0.0, -0.08, 0.0]
    bonus = tolerance(0.08, bounds=(0, 0.05), margin=0.3, sigmoid="long_tail")
    assert reward(reach, info_at(now, now, init)) == pytest.approx(bonus)
    inside = REACH_GOAL + [0.0, -0.02, 0.0]
    assert reward(reach, info_at(inside, inside, init)) == pytest.approx(1.0)


def test_opposite_behaviour_runs_in_the_opposite_task_with_its_own_reward_and_success():
    opposite = get_target("opposite")
    assert opposite.env_task("drawer-open-v3") == "drawer-close-v3"
    assert opposite.env_task("door-lock-v3") == "door-unlock-v3"
    assert reward(opposite, {"task_reward": 3.5}) == 3.5
    assert opposite.success({"success": True}) and not opposite.success({"success": False})
    with pytest.raises(RatError, match="no opposite"):
        opposite_task("reach-v3")


def test_reach_reward_on_the_real_environment_rewards_moving_towards_the_goal():
    env = make_task("drawer-open-v3")
    reach = get_target("reach")
    obs, info = env.reset(seed=0)
    towards = REACH_GOAL - info["tcp_pos"]
    next_obs, _, _, _, info = env.step(np.r_[np.sign(towards), 0.0])
    assert reach.reward(obs, None, next_obs, info) > 0


def test_user_registered_target_is_found_and_listed():
    @register_target("test-lift", success=lambda info: info["tcp_pos"][2] > 0.3, description="lift")
    def lift(obs, action, next_obs, info):
        return info["tcp_pos"][2] - info["prev_tcp_pos"][2]

    try:
        t = get_target("test-lift")
        assert t.success(info_at([0, 0, 0.4])) and not t.success(info_at([0, 0, 0.2]))
        assert reward(t, info_at([0, 0, 0.4], [0, 0, 0.3])) == pytest.approx(0.1)
        assert "test-lift" in [x.name for x in list_targets()]
        with pytest.raises(RatError, match="already registered"):
            register_target("test-lift", success=bool)(lift)
    finally:
        _REGISTRY.items.pop("test-lift")


def test_unknown_target_names_the_fix():
    with pytest.raises(RatError, match="rat list targets"):
        get_target("fly")
