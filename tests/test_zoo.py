import json

import pytest

from rat.envs import PAPER_TASKS, make_task
from rat.eval import evaluate
from rat.victims import check_compatible, load_victim, zoo_tasks
from rat.victims.base import numpy_policy
from rat.victims.zoo import ZOO_DIR


def test_the_zoo_holds_a_victim_for_each_paper_task():
    assert zoo_tasks() == sorted(PAPER_TASKS)


@pytest.mark.parametrize("task", sorted(PAPER_TASKS))
def test_zoo_victim_loads_records_its_provenance_and_succeeds(task):
    victim = load_victim(f"zoo:{task}")
    meta = victim.meta
    assert meta["task"] == task and meta["method"] in ("bc", "sac", "sac-demo") and meta["commit"]
    assert meta["clean_eval"]["episodes"] >= 50 and meta["clean_eval"]["success_rate"] >= 0.95
    env = make_task(task, seed=123)
    check_compatible(victim, env)
    result = evaluate(numpy_policy(victim), env, episodes=3, seed=777, stop_at_success=True)
    assert result.success_rate == 1.0, result.summary()


def test_zoo_timings_are_recorded():
    timings = json.loads((ZOO_DIR / "timings.json").read_text())
    for task in PAPER_TASKS:
        assert timings[task]["minutes"] > 0 and timings[task]["clean_success"] >= 0.95
