"""People label the target behaviour: the query queue of the label store, the labelling server,
a run that waits for answers given over HTTP, and the page in a real Chromium."""

import shutil
import sqlite3
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from rat.agents.sac import SACConfig
from rat.errors import RatError
from rat.preferences.labeller import QueryRound
from rat.preferences.pebble import PebbleConfig
from rat.preferences.segments import SegmentPairs
from rat.preferences.store import AnswerError, LabelStore
from rat.preferences.teacher import ScriptedTeacher, TeacherConfig

fastapi = pytest.importorskip("fastapi", reason="the labelling page needs: pip install 'rat[web]'")


def pairs(n=4, length=5, seed=0, physics=True):
    rng = np.random.default_rng(seed)
    arrays = [rng.normal(size=s).astype(np.float32) for s in [(n, length, 3), (n, length, 2), (n, length)] * 2]
    extra = (rng.normal(size=(n, length, 7)), rng.normal(size=(n, length, 7)), rng.normal(size=(n, 4)),
             rng.normal(size=(n, 4))) if physics else None
    return SegmentPairs(*arrays, physics=extra)


def published(tmp_path, n=4):
    store = LabelStore(tmp_path / "labels.sqlite")
    ids = store.publish(pairs(n), "run-a", round=0, step=100, task="drawer-close-v3", target="reach")
    return store, ids


# --- the query queue ---------------------------------------------------------------------------------


def test_answers_are_stored_once_with_who_when_and_how_long(tmp_path):
    store, ids = published(tmp_path)
    assert store.publish(pairs(4, seed=9), "run-a", round=0, step=100) == ids  # a resumed run republishes nothing
    label_id = store.answer(ids[0], "right", {"type": "human", "name": "ada"}, duration_s=3.5)
    assert store.answer(ids[1], "skip", {"type": "human", "name": "ada"}) is None
    store.answer(ids[2], "equal", {"type": "human", "name": "bob"}, duration_s=1.0)
    with pytest.raises(AnswerError, match="already answered") as exc:
        store.answer(ids[0], "left", {"type": "human", "name": "bob"})
    assert exc.value.status == 409
    with pytest.raises(AnswerError, match="no query 999") as exc:
        store.answer(999, "left", {"type": "human"})
    assert exc.value.status == 404
    with pytest.raises(AnswerError, match="unknown answer 'maybe'") as exc:
        store.answer(ids[3], "maybe", {"type": "human"})
    assert exc.value.status == 422

    rows = store.read("run-a").rows
    assert [r["id"] for r in rows] == [label_id, label_id + 1]
    assert rows[0]["labeller"] == {"type": "human", "name": "ada"} and rows[0]["duration_s"] == 3.5
    assert rows[0]["query_id"] == ids[0] and rows[0]["label"] == 1.0 and rows[1]["label"] == 0.5
    stored = store.read("run-a").pairs
    np.testing.assert_array_equal(stored.obs0[0], pairs(4).obs0[0])  # the query's own segments
    assert [q["answer"] for q in store.queries("run-a")] == ["right", "skip", "equal", None]


def test_undo_withdraws_the_labellers_own_latest_answer_until_the_round_closes(tmp_path):
    store, ids = published(tmp_path)
    store.answer(ids[0], "left", {"type": "human", "name": "ada"})
    store.answer(ids[1], "right", {"type": "human", "name": "bob"})
    store.answer(ids[2], "skip", {"type": "human", "name": "ada"})
    assert store.undo("ada") == ids[2]  # ada's latest, not bob's
    assert store.undo("ada") == ids[0]
    assert store.undo("ada") is None
    assert store.count() == 1
    store.answer(ids[0], "right", {"type": "human", "name": "ada"})  # answered again after the undo

    index, y = store.close_round("run-a", 0, step=100)
    assert index.tolist() == [0, 1] and y.tolist() == [1.0, 1.0]
    assert store.rounds("run-a") == [dict(store.rounds("run-a")[0], asked=4, answered=2)]
    assert store.undo("bob") is None  # closed rounds keep their answers
    with pytest.raises(AnswerError, match="closed round") as exc:
        store.answer(ids[3], "left", {"type": "human"})
    assert exc.value.status == 409


def test_published_segments_and_physics_come_back_exactly(tmp_path):
    store, ids = published(tmp_path)
    back, sent = store.query_pairs(ids[::-1]), pairs(4).select([3, 2, 1, 0])
    for a, b in zip(back.arrays() + back.physics, sent.arrays() + sent.physics):
        np.testing.assert_array_equal(a, b)


def test_only_recorded_videos_inside_the_store_folder_are_served(tmp_path):
    store, ids = published(tmp_path)
    (tmp_path / "queries").mkdir()
    (tmp_path / "queries" / "a.mp4").write_bytes(b"x")
    (tmp_path.parent / "secret.mp4").write_bytes(b"y")
    store.set_videos(ids[0], "queries/a.mp4", "../secret.mp4")
    assert store.video_path(ids[0], 0) == (tmp_path / "queries" / "a.mp4").resolve()
    assert store.video_path(ids[0], 1) is None  # outside the store's folder
    assert store.video_path(ids[0], 2) is None and store.video_path(ids[1], 0) is None


def test_a_schema_1_store_is_upgraded_in_place_and_keeps_its_labels(tmp_path):
    path = tmp_path / "old.sqlite"
    with LabelStore(path) as store:
        store.add(pairs(2, physics=False), np.array([1.0, 0.0]), {"type": "scripted"}, "old-run", round=0,
                  step=10, asked=2)
    db = sqlite3.connect(path)  # what schema 1 looked like
    db.executescript("DROP INDEX labels_by_query; ALTER TABLE labels DROP COLUMN query_id; "
                     "ALTER TABLE labels DROP COLUMN duration_s; DROP TABLE queries; DROP TABLE answers; "
                     "UPDATE store_info SET value='1' WHERE key='schema_version';")
    db.close()
    with LabelStore(path, read_only=True) as old:
        assert old.schema == 1 and len(old.read()) == 2  # read as it is, nothing written
    with LabelStore(path) as store:
        assert store.schema == 2 and store.read().y.tolist() == [1.0, 0.0]
        assert store.publish(pairs(1), "new-run", 0, 5)  # and it takes queries now


# --- the server ----------------------------------------------------------------------------------


@pytest.fixture
def client(tmp_path):
    from fastapi.testclient import TestClient

    from rat.labelling.server import create_app

    store, ids = published(tmp_path)
    (tmp_path / "queries").mkdir()
    for i in ids[:3]:
        for side in (0, 1):
            (tmp_path / "queries" / f"{i}-{side}.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42")
        store.set_videos(i, f"queries/{i}-0.mp4", f"queries/{i}-1.mp4")
    store.close()
    return TestClient(create_app(tmp_path / "labels.sqlite")), ids


def test_the_api_serves_ready_queries_takes_answers_and_undoes_them(client):
    client, ids = client
    assert "Which segment shows the target behaviour better?" in client.get("/").text
    state = client.get("/api/state").json()
    assert [q["id"] for q in state["queries"]] == ids[:3]  # the fourth is still being filmed
    assert state["round"] == {"total": 4, "answered": 0, "filming": 1, "rounds": ["run-a round 0"]}
    assert client.get(f"/{state['queries'][0]['videos'][1]}").content.endswith(b"ftypmp42")

    r = client.post("/api/answers", json={"query_id": ids[0], "choice": "left", "labeller": "ada", "duration_s": 2.0})
    assert r.status_code == 201 and r.json()["label_id"] == 1
    assert client.post("/api/answers", json={"query_id": ids[0], "choice": "right"}).status_code == 409
    assert client.post("/api/answers", json={"query_id": 12345, "choice": "right"}).status_code == 404
    assert client.post("/api/answers", json={"query_id": ids[1], "choice": "upward"}).status_code == 422
    assert client.post("/api/answers", json={"query_id": "one", "choice": "left"}).status_code == 422
    assert client.post("/api/answers", content=b"{not json").status_code == 422
    assert client.post("/api/answers", json={"query_id": ids[1], "choice": "left", "duration_s": -1}).status_code == 422
    assert client.get("/api/state").json()["round"]["answered"] == 1

    assert client.post("/api/undo", json={"labeller": "bob"}).status_code == 404
    assert client.post("/api/undo", json={"labeller": "ada"}).json() == {"query_id": ids[0]}
    assert client.get("/api/state").json()["round"]["answered"] == 0


@pytest.mark.parametrize("path", ["/videos/../../labels.sqlite", "/videos/1/..%2F..%2Flabels.sqlite",
                                  "/videos/%2e%2e/%2e%2e/etc/passwd", "/videos/1/2", "/videos/1/-1", "/videos/-1/0",
                                  "/videos/4/0", "/../labels.sqlite", "/labels.sqlite", "/queries/1-0.mp4"])
def test_path_traversal_finds_nothing(client, path):
    client, _ = client
    assert client.get(path).status_code == 404


def test_off_loopback_every_request_needs_the_token(tmp_path):
    from fastapi.testclient import TestClient

    from rat.labelling import WebLabellingConfig
    from rat.labelling.server import create_app

    published(tmp_path)[0].close()
    config = WebLabellingConfig(host="0.0.0.0").with_token()
    assert config.token and f"?token={config.token}" in config.url()
    client = TestClient(create_app(tmp_path / "labels.sqlite", config.token))
    for path in ("/", "/api/state", "/videos/1/0", f"/api/state?token={config.token[:-1]}{'y' if config.token.endswith('x') else 'x'}"):
        assert client.get(path).status_code == 401
    assert client.post("/api/answers", json={"query_id": 1, "choice": "left"}).status_code == 401
    assert client.get(f"/api/state?token={config.token}").status_code == 200
    assert client.get("/api/state", headers={"Authorization": f"Bearer {config.token}"}).status_code == 200
    assert LabelStore(tmp_path / "labels.sqlite").count() == 0


def test_bad_labelling_settings_are_one_line_errors(tmp_path):
    from rat.labelling import WebLabellingConfig
    from rat.labelling.server import create_app

    with pytest.raises(RatError, match="timeout must be positive"):
        WebLabellingConfig(timeout_s=0)
    with pytest.raises(RatError, match="no label store at"):
        create_app(tmp_path / "missing.sqlite")


# --- a run waits for a person --------------------------------------------------------------------

TINY = dict(total_steps=400, eval_every=10**6, eval_episodes=1, final_eval_episodes=1, quality_episodes=1,
            checkpoint_every=100)
TINY_PEBBLE = PebbleConfig(sac=SACConfig(batch_size=32, hidden=32, layers=2), seed_steps=100, unsupervised_steps=100,
                           budget=6, per_round=3, feedback_every=100, segment_length=8, candidates_factor=2,
                           max_episodes=5, reset_updates=5, teacher=TeacherConfig(ties=True))


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class SimulatedPerson(threading.Thread):
    """Answers every query it is shown over HTTP with the noise-free scripted teacher's label,
    reading the query's true target reward from the store (which a person would judge by eye)."""

    def __init__(self, url: str, store_path: Path, stop: threading.Event):
        super().__init__(daemon=True)
        self.url, self.store_path, self.stop, self.answered, self.errors = url, store_path, stop, {}, []

    def run(self):
        import httpx

        teacher = ScriptedTeacher(TeacherConfig(ties=True))
        while not self.stop.is_set():
            try:
                state = httpx.get(self.url + "api/state", timeout=10).json()
                for q in state["queries"]:
                    assert httpx.get(self.url + q["videos"][0], timeout=10).content[4:8] == b"ftyp"
                    with LabelStore(self.store_path) as store:
                        y = teacher.label(store.query_pairs([q["id"]]), np.random.default_rng(0)).y[0]
                    choice = {0.0: "left", 1.0: "right", 0.5: "equal"}[float(y)]
                    r = httpx.post(self.url + "api/answers", timeout=10,
                                   json={"query_id": q["id"], "choice": choice, "labeller": "sim", "duration_s": 0.1})
                    assert r.status_code == 201, r.text
                    self.answered[q["id"]] = float(y)
            except Exception as exc:  # noqa: BLE001 - reported by the test
                self.errors.append(repr(exc))
            time.sleep(0.2)


@pytest.mark.slow
def test_an_intention_run_completes_its_rounds_with_answers_given_over_http(tmp_path):
    from rat.labelling import WebLabeller, WebLabellingConfig
    from rat.preferences.intention import IntentionConfig, train_intention

    out, port = tmp_path / "run", free_port()
    config = IntentionConfig(task="drawer-close-v3", pebble=TINY_PEBBLE, **TINY)
    labeller = WebLabeller(out / "labels.sqlite", WebLabellingConfig(port=port, frame_size=32, poll_s=0.1),
                           progress=False)
    labeller.serve()
    stop = threading.Event()
    person = SimulatedPerson(f"http://127.0.0.1:{port}/", out / "labels.sqlite", stop)
    person.start()
    report = train_intention(config, out, progress=False, labeller=labeller)
    stop.set()
    person.join()
    assert person.errors == []
    with LabelStore(out / "labels.sqlite") as store:
        labels = store.read()
        assert [r["answered"] for r in store.rounds(out.name)] == [3, 3] and report.labels == 6
        assert {r["query_id"]: r["label"] for r in labels.rows} == person.answered  # every answer, once
        assert all(r["labeller"] == {"type": "human", "name": "sim", "via": "web"} for r in labels.rows)
        expected = ScriptedTeacher(TeacherConfig(ties=True)).label(labels.pairs, np.random.default_rng(0)).y
        np.testing.assert_array_equal(labels.y, expected)  # what the teacher would have given
        assert all(q["closed"] for q in store.queries(open_only=False))
        assert len(list((out / "queries").rglob("*.mp4"))) == 12
        # a run interrupted after closing a round asks it again on resume: it gets the same labels at once
        query = QueryRound(1, 300, out.name, "drawer-close-v3", "reach")
        again = labeller.label(store.query_pairs(store.query_ids(out.name, 1)), np.random.default_rng(0), query)
        assert again.y.tolist() == labels.y[3:].tolist() and store.count() == 6


@pytest.mark.slow
def test_after_the_timeout_the_teacher_answers_the_rest_and_a_resumed_run_keeps_every_answer(tmp_path):
    from rat.labelling import WebLabeller, WebLabellingConfig
    from rat.preferences import intention

    out, port = tmp_path / "run", free_port()
    config = intention.IntentionConfig(task="drawer-close-v3", pebble=replace(TINY_PEBBLE, budget=3), **TINY)
    web = WebLabellingConfig(port=port, frame_size=32, poll_s=0.1, timeout_s=1.0, fallback=True, serve=False)

    class Killed(Exception):
        pass

    killer = WebLabeller(out / "labels.sqlite", replace(web, timeout_s=None), progress=False)
    real_wait = WebLabeller._wait

    def answer_one_then_die(self, store, ids, rng, query):
        store.answer(ids[0], "equal", {"type": "human", "name": "ada"}, 4.0)
        raise Killed  # the run dies while it waits

    killer._wait = answer_one_then_die.__get__(killer)
    with pytest.raises(Killed):
        intention.train_intention(config, out, progress=False, labeller=killer)
    labeller = WebLabeller(out / "labels.sqlite", web, progress=False)
    assert labeller._wait.__func__ is real_wait
    intention.train_intention(config, out, progress=False, labeller=labeller)
    with LabelStore(out / "labels.sqlite") as store:
        rows = store.read().rows
        assert len(store.queries(open_only=False)) == 3  # the resumed run republished nothing
        assert rows[0]["labeller"]["name"] == "ada" and rows[0]["label"] == 0.5
        assert all(r["labeller"]["type"] == "scripted" for r in rows[1:])
        assert len(store.db.execute("SELECT * FROM answers").fetchall()) == 3


# --- the page in a real browser ----------------------------------------------------------------------

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.slow
def test_the_page_in_chromium_plays_both_videos_and_takes_keyboard_mouse_and_undo(tmp_path):
    if CHROMIUM is None:
        pytest.skip("no Chromium: install it with `sudo apt-get install chromium` (make test does where it can)")
    playwright = pytest.importorskip("playwright.sync_api", reason="pip install playwright (the dev extra has it)")
    from rat.eval import write_video
    from rat.labelling import WebLabellingConfig
    from rat.labelling.server import start_server

    store, ids = published(tmp_path)
    for i in ids:
        frames = [np.full((32, 32, 3), 40 * k, np.uint8) for k in range(6)]
        for side in (0, 1):
            write_video(frames, tmp_path / "queries" / f"{i}-{side}.mp4", fps=10)
        store.set_videos(i, f"queries/{i}-0.mp4", f"queries/{i}-1.mp4")
    port = free_port()
    start_server(tmp_path / "labels.sqlite", WebLabellingConfig(port=port))
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--autoplay-policy=no-user-gesture-required"])
        page = browser.new_page()
        page.goto(f"http://127.0.0.1:{port}/?name=tester")
        page.wait_for_function("document.getElementById('meta').textContent.includes('pair 1')")
        for side in ("left", "right"):  # both videos load and play
            page.wait_for_function(f"(() => {{ const v = document.getElementById('video-{side}'); "
                                   "return v.readyState >= 2 && v.currentTime > 0 && !v.paused; })()", timeout=20_000)
        page.keyboard.press("ArrowRight")  # pair 1: right, by keyboard
        page.wait_for_function("document.getElementById('meta').textContent.includes('pair 2')")
        page.click("#btn-left")  # pair 2: left, by mouse
        page.wait_for_function("document.getElementById('meta').textContent.includes('pair 3')")
        page.keyboard.press("e")  # pair 3: equally good
        page.wait_for_function("document.getElementById('meta').textContent.includes('pair 4')")
        page.keyboard.press("u")  # undo pair 3
        page.wait_for_function("document.getElementById('status').textContent.includes('undone')")
        page.wait_for_function("document.getElementById('meta').textContent.includes('pair 3')")
        page.keyboard.press("s")  # pair 3 again: can't tell
        page.wait_for_function("document.getElementById('meta').textContent.includes('pair 4')")
        page.screenshot(path=str(tmp_path / "page.png"))
        browser.close()
    rows = store.read().rows
    assert [(r["query_id"], r["label"]) for r in rows] == [(ids[0], 1.0), (ids[1], 0.0)]
    assert all(r["labeller"]["name"] == "tester" and r["duration_s"] > 0 for r in rows)
    assert [q["answer"] for q in store.queries()] == ["right", "left", "skip", None]


# --- load, and the server killed mid-round -------------------------------------------------------------


@pytest.mark.slow
def test_concurrent_answers_are_stored_exactly_once_and_a_killed_server_loses_none_acknowledged(tmp_path):
    from benchmark_scripts import load as load_script

    load = load_script("labelling_load")
    r = load.run(clients=8, answers=40, kill_at=100, folder=tmp_path)
    assert r["error_count"] == 0, r["errors"]
    assert 100 <= r["acknowledged_before_kill"] < 320  # killed mid-round, then restarted
    assert r["acknowledged"] <= r["stored_answers"] == 320 and r["unanswered"] == 0
    assert r["acknowledged_but_lost"] == 0 and r["duplicates"] == 0
