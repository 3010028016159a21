import json

import numpy as np
import pytest
import torch

from rat.agents.sac import SAC, SACConfig
from rat.checkpoint import load_checkpoint, save_checkpoint
from rat.errors import RatError


def small_agent():
    torch.manual_seed(0)
    agent = SAC(3, 2, SACConfig(hidden=8, layers=1, batch_size=4))
    batch = {"obs": torch.randn(4, 3), "action": torch.rand(4, 2) * 2 - 1, "reward": torch.randn(4),
             "next_obs": torch.randn(4, 3), "terminated": torch.zeros(4)}
    agent.update(batch)  # gives the optimisers some state
    return agent


def test_round_trip_of_networks_optimisers_and_arrays(tmp_path):
    agent = small_agent()
    state = {"agent": agent.state_dict(), "optimizers": agent.optimizer_state(),
             "array": np.arange(6.0).reshape(2, 3), "nested": [1, (2, "x"), {"k": None}]}
    save_checkpoint(tmp_path / "ck", "test", state, {"note": "hello"})
    loaded, meta = load_checkpoint(tmp_path / "ck", "test")
    assert meta == {"note": "hello"}
    clone = SAC(3, 2, SACConfig(hidden=8, layers=1, batch_size=4))
    clone.load_state_dict(loaded["agent"])
    clone.load_optimizer_state(loaded["optimizers"])
    for (k, a), b in zip(agent.state_dict().items(), clone.state_dict().values()):
        torch.testing.assert_close(a, b, msg=k)
    assert clone.updates == agent.updates == 1
    assert clone.actor_opt.state_dict()["state"].keys() == agent.actor_opt.state_dict()["state"].keys()
    np.testing.assert_array_equal(loaded["array"], state["array"])
    assert loaded["nested"] == [1, (2, "x"), {"k": None}]


def test_a_checkpoint_is_two_plain_files_and_no_pickle(tmp_path):
    save_checkpoint(tmp_path / "ck", "test", {"w": torch.ones(2)}, {})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ck.json", "ck.safetensors"]
    assert json.loads((tmp_path / "ck.json").read_text())["format"] == "rat-checkpoint"


@pytest.mark.parametrize("damage, message", [
    ("json", "corrupted"),
    ("tensors", "unreadable or corrupted"),
    ("foreign", "not a rat checkpoint"),
    ("missing", "no checkpoint at"),
])
def test_damaged_checkpoints_give_one_line_errors(tmp_path, damage, message):
    path = save_checkpoint(tmp_path / "ck", "test", {"w": torch.ones(1000)}, {})
    if damage == "json":
        path.with_suffix(".json").write_text('{"format": "rat-checkp')
    elif damage == "tensors":
        data = path.with_suffix(".safetensors").read_bytes()
        path.with_suffix(".safetensors").write_bytes(data[: len(data) // 2])
    elif damage == "foreign":
        path.with_suffix(".json").write_text('{"model": "something else"}')
    else:
        path.with_suffix(".json").unlink()
    with pytest.raises(RatError, match=message) as info:
        load_checkpoint(path, "test")
    assert "\n" not in str(info.value)


def test_a_part_of_a_checkpoint_reads_only_its_own_tensors(tmp_path, monkeypatch):
    import safetensors

    state = {"learner": {"ensemble": {"w": torch.arange(3.0), "b": [torch.ones(2)]}, "buffer": torch.zeros(10_000)}}
    save_checkpoint(tmp_path / "ck", "test", state, {"step": 5})
    read = []
    real_open = safetensors.safe_open

    class Recording:
        def __init__(self, *args, **kwargs):
            self.handle = real_open(*args, **kwargs)

        def __enter__(self):
            self.inner = self.handle.__enter__()
            return self

        def __exit__(self, *exc):
            return self.handle.__exit__(*exc)

        def keys(self):
            return self.inner.keys()

        def get_tensor(self, name):
            read.append(name)
            return self.inner.get_tensor(name)

    monkeypatch.setattr("rat.checkpoint.safe_open", Recording)
    part, meta = load_checkpoint(tmp_path / "ck", "test", part=("learner", "ensemble"))
    assert meta == {"step": 5}
    torch.testing.assert_close(part["w"], torch.arange(3.0))
    torch.testing.assert_close(part["b"][0], torch.ones(2))
    assert sorted(read) == ["state/learner/ensemble/b/0", "state/learner/ensemble/w"]  # not the buffer
    with pytest.raises(RatError, match="holds no 'learner/reward' \\(no 'reward'\\)"):
        load_checkpoint(tmp_path / "ck", "test", part=("learner", "reward"))


def test_kind_is_checked(tmp_path):
    save_checkpoint(tmp_path / "ck", "victim", {}, {})
    with pytest.raises(RatError, match="'victim' checkpoint, not a 'sac-run' one"):
        load_checkpoint(tmp_path / "ck", "sac-run")


class Counter:
    """The smallest :class:`~rat.loop.Trainer`: one unit a step, each taking ``seconds`` of a fake clock."""

    kind, finished = "counter", False

    def __init__(self, clock: list[float], seconds: float, die_at: int | None = None):
        self.step, self.clock, self.seconds, self.die_at = 0, clock, seconds, die_at

    def advance(self):
        if self.step == self.die_at:
            raise KeyboardInterrupt  # the session ends
        self.clock[0] += self.seconds
        self.step += 1
        return {"x": float(self.step)}

    def evaluate(self):
        return {}

    def state_dict(self):
        return {"step": np.array([self.step])}

    def load_state_dict(self, state, meta):
        self.step = int(meta["step"])

    def checkpoint_meta(self):
        return {}


def test_a_resumed_run_counts_the_training_time_of_every_session(tmp_path, monkeypatch):
    from rat import loop as loop_module
    from rat.loop import TrainingLoop
    from rat.runs import Run

    clock = [0.0]
    monkeypatch.setattr(loop_module.time, "perf_counter", lambda: clock[0])
    first = TrainingLoop(Run(tmp_path, {"n": 10}), Counter(clock, 2.0, die_at=7), 10, eval_every=None,
                         checkpoint_every=5, progress=False)
    with pytest.raises(KeyboardInterrupt):
        first.run()  # 7 units, 14 s; the checkpoint at unit 5 holds 10 s
    assert load_checkpoint(tmp_path / "checkpoint", "counter")[1]["seconds"] == 10.0
    second = TrainingLoop(Run(tmp_path, {"n": 10}), Counter(clock, 3.0), 10, eval_every=None, checkpoint_every=5,
                          progress=False)
    assert second.resume() and second.trainer.step == 5
    assert second.run() == 15.0  # this session: units 6-10 at 3 s
    assert second.total_seconds == 25.0  # and the 10 s that made the checkpoint it resumed (units 6-7's lost 4 s are not)


def test_the_commit_a_run_records_is_read_once_so_a_checkout_moved_later_does_not_change_it(monkeypatch):
    import subprocess

    from rat import runs

    calls = []
    real = subprocess.run
    monkeypatch.setattr(subprocess, "run", lambda *a, **k: calls.append(a) or real(*a, **k))
    runs.git_commit.cache_clear()
    try:
        first = runs.git_commit()
        assert runs.git_commit() == first and len(calls) == 1
    finally:
        runs.git_commit.cache_clear()
