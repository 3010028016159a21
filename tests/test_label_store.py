import os
import signal
import sqlite3
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from rat.errors import RatError
from rat.preferences.segments import SegmentPairs
from rat.preferences.store import LabelStore


def random_pairs(n, rng, length=5):
    return SegmentPairs(rng.normal(size=(n, length, 3)).astype(np.float32), rng.normal(size=(n, length, 2)).astype(np.float32),
                        rng.normal(size=(n, length)).astype(np.float32), rng.normal(size=(n, length, 3)).astype(np.float32),
                        rng.normal(size=(n, length, 2)).astype(np.float32), rng.normal(size=(n, length)).astype(np.float32))


def test_labels_round_trip_with_segments_labeller_and_time(tmp_path, rng):
    pairs = random_pairs(4, rng)
    with LabelStore(tmp_path / "l.sqlite") as store:
        ids = store.add(pairs, np.array([1.0, 0.0, 0.5, 1.0]), {"type": "scripted", "beta": None}, "run-a",
                        round=0, task="drawer-open-v3", target="reach", step=100, asked=5)
        got = store.read("run-a")
    assert ids == [1, 2, 3, 4] and got.y.tolist() == [1.0, 0.0, 0.5, 1.0]
    for a, b in zip(got.pairs.arrays(), pairs.arrays()):
        np.testing.assert_array_equal(a, b)
    assert got.rows[0]["labeller"] == {"type": "scripted", "beta": None} and got.rows[0]["created_at"].endswith("+00:00")
    with LabelStore(tmp_path / "l.sqlite") as store:
        assert store.rounds("run-a") == [{"round": 0, "step": 100, "asked": 5, "answered": 4,
                                          "created_at": got.rows[0]["created_at"]}]


WRITER = textwrap.dedent("""
    import sys, numpy as np
    from rat.preferences.store import LabelStore
    from rat.preferences.segments import SegmentPairs
    store = LabelStore(sys.argv[1])
    rng = np.random.default_rng(0)
    for i in range(100000):
        a = rng.normal(size=(1, 50, 39)).astype(np.float32)
        act = rng.normal(size=(1, 50, 4)).astype(np.float32)
        r = rng.normal(size=(1, 50)).astype(np.float32)
        ids = store.add(SegmentPairs(a, act, r, a, act, r), np.array([float(i % 2)]), {"type": "scripted"}, "w")
        print(ids[0], flush=True)  # acknowledged: the transaction committed
""")


def test_a_killed_writer_loses_no_acknowledged_label(tmp_path):
    path = tmp_path / "labels.sqlite"
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, text=True)
    acked = []
    for line in proc.stdout:
        acked.append(int(line))
        if len(acked) == 200:
            break
    os.kill(proc.pid, signal.SIGKILL)  # at an arbitrary point of the next write
    proc.wait()
    with LabelStore(path) as store:
        labels = store.read("w")
        ids = [r["id"] for r in labels.rows]
    assert set(acked) <= set(ids)
    assert labels.y[:200].tolist() == [float(i % 2) for i in range(200)]
    assert ids == list(range(1, len(ids) + 1))  # no torn or partial rows


def test_export_and_import_keep_labels_and_provenance(tmp_path, rng):
    with LabelStore(tmp_path / "a.sqlite") as a:
        a.add(random_pairs(3, rng), np.array([1.0, 0.0, 1.0]), {"type": "scripted"}, "rat-run", round=0, step=10, asked=3)
        a.add(random_pairs(2, rng), np.array([0.0, 0.0]), {"type": "human", "name": "ana"}, "other")
        assert a.export_to(tmp_path / "export.sqlite", source="rat-run") == 3
        original = a.read("rat-run")
    with LabelStore(tmp_path / "b.sqlite") as b:
        assert b.import_from(tmp_path / "export.sqlite", source="sa-rl-run") == 3
        copied = b.read("sa-rl-run")
    for x, y in zip(copied.pairs.arrays(), original.pairs.arrays()):
        np.testing.assert_array_equal(x, y)
    assert copied.y.tolist() == original.y.tolist()
    assert copied.rows[0]["imported_from"].endswith("export.sqlite#1")
    assert copied.rows[0]["created_at"] == original.rows[0]["created_at"]
    with LabelStore(tmp_path / "b.sqlite") as b:  # the round accounting came along, under the new name
        assert [(r["round"], r["step"], r["asked"], r["answered"]) for r in b.rounds("sa-rl-run")] == [(0, 10, 3, 3)]
    with pytest.raises(RatError, match="already exists"):
        LabelStore(tmp_path / "a.sqlite").export_to(tmp_path / "export.sqlite")


def test_a_file_that_is_not_a_store_is_a_one_line_error(tmp_path):
    bad = tmp_path / "bad.sqlite"
    bad.write_bytes(b"this is not a database" * 100)
    with pytest.raises(RatError, match="not a readable label store"):
        LabelStore(bad)


def test_reading_a_store_read_only_never_writes_to_it(tmp_path, rng):
    with LabelStore(tmp_path / "l.sqlite") as store:
        store.add(random_pairs(2, rng), np.array([1.0, 0.0]), {"type": "scripted"}, "run", round=0, step=1, asked=2)
    before = (tmp_path / "l.sqlite").read_bytes()
    with LabelStore(tmp_path / "l.sqlite", read_only=True) as store:
        assert store.count() == 2 and store.rounds("run")[0]["asked"] == 2
        with pytest.raises(sqlite3.OperationalError, match="readonly"):
            store.add(random_pairs(1, rng), np.array([1.0]), {"type": "scripted"}, "run")
    assert (tmp_path / "l.sqlite").read_bytes() == before


def test_the_label_returns_script_summarises_what_each_round_showed_the_teacher(tmp_path, rng):
    from benchmark_scripts import load

    label_returns = load("label_returns")
    early, late = random_pairs(2, rng), random_pairs(1, rng)
    early.reward0[:], early.reward1[:], late.reward0[:], late.reward1[:] = 1.0, 2.0, 3.0, 1.0
    late.reward1[0, 2] = 10.0  # one step of one segment inside the success region
    with LabelStore(tmp_path / "l.sqlite") as store:
        store.add(early, np.array([1.0, 1.0]), {"type": "scripted"}, "run", round=0, step=100, asked=2)
        store.add(late, np.array([1.0]), {"type": "scripted"}, "run", round=1, step=200, asked=1)
        store.add(late, np.array([0.0]), {"type": "scripted"}, "imported", round=0, step=50, asked=1)
        other, first, second = label_returns.round_summaries(store, high=9.0)
    assert (other["source"], other["round"], other["step"], other["pairs"]) == ("imported", 0, 50, 1)  # kept apart
    assert (first["step"], first["pairs"], first["max_step"], first["share_high"]) == (100, 2, 2.0, 0.0)
    assert first["return_max"] == 10.0 and first["return_p50"] == 7.5  # segments of 5 steps: returns 5, 5, 10, 10
    assert (second["step"], second["pairs"], second["max_step"], second["share_high"]) == (200, 1, 10.0, 0.5)
    assert second["return_max"] == 15.0 and second["return_p50"] == 14.5  # 3 × 5 steps, and 4 × 1 + 10
