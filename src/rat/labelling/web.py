"""The web labeller: a person answers each query round on the labelling page.

At a query round, :meth:`WebLabeller.label`

1. publishes the round's queries in the run's label store (a run resumed while it waited finds
   them there, with every answer given so far, and publishes nothing new);
2. films both segments of every query from their recorded physics states, in order, so the
   first queries can be answered while later ones are filmed;
3. waits, showing in the terminal where to label and how many are answered, until every query
   is answered or skipped — or, with ``timeout_s``, until that many seconds have passed, when
   the scripted teacher answers the rest if ``fallback`` asks for it (they are skipped if not);
4. closes the round and returns its labels, which are already in the store, one row per answer,
   with who gave it, when and how long it took.
"""

from __future__ import annotations

import secrets
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from rat.errors import RatError
from rat.preferences.labeller import Labels, QueryRound
from rat.preferences.segments import SegmentPairs
from rat.preferences.store import AnswerError, LabelStore
from rat.preferences.teacher import ScriptedTeacher

LOOPBACK = ("127.0.0.1", "localhost", "::1")


@dataclass(frozen=True)
class WebLabellingConfig:
    """How a run asks a person for labels."""

    host: str = "127.0.0.1"  #: address the page is served on; any other than loopback requires a token
    port: int = 8765  #: port of the page
    token: str | None = None  #: access token (required, and generated if not given, off loopback)
    timeout_s: float | None = None  #: seconds a round waits for answers (None: until all are answered)
    fallback: bool = False  #: after the timeout, the scripted teacher answers what is left (else: skipped)
    frame_size: int = 192  #: pixels of the filmed segments (square, Meta-World)
    fps: int = 20  #: frames per second of the filmed segments
    poll_s: float = 0.5  #: seconds between looks at the store while waiting
    serve: bool = True  #: serve the page from the run's own process (False: run `rat label serve` yourself)

    def __post_init__(self):
        if self.timeout_s is not None and self.timeout_s <= 0:
            raise RatError(f"the labelling timeout must be positive seconds, got {self.timeout_s}")
        if not 0 < self.port < 65536:
            raise RatError(f"port must lie in 1-65535, got {self.port}")
        if self.frame_size < 16 or self.fps <= 0 or self.poll_s <= 0:
            raise RatError("frame-size must be >= 16 pixels, fps and poll-s positive")

    @property
    def needs_token(self) -> bool:
        return self.host not in LOOPBACK

    def with_token(self) -> WebLabellingConfig:
        """This configuration with a token generated where one is needed and none was given."""
        if self.needs_token and not self.token:
            return replace(self, token=secrets.token_urlsafe(24))
        return self

    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/" + (f"?token={self.token}" if self.token else "")


class WebLabeller:
    """A :class:`~rat.preferences.labeller.Labeller` whose answers come from a person on the labelling page.

    Args:
        store_path: the run's label store (the page serves it; answers go into it).
        config: where to serve and how long to wait.
        teacher: the scripted teacher that answers after a timeout, with ``config.fallback``.
        progress: show the round's progress in the terminal.
    """

    films_segments = True  # the run records physics states, so the segments can be filmed
    stores_labels = True  # every answer is written to the store as it is given

    def __init__(self, store_path: str | Path, config: WebLabellingConfig = WebLabellingConfig(),
                 teacher: ScriptedTeacher | None = None, progress: bool = True):
        self.store_path, self.config = Path(store_path), config.with_token()
        self.teacher, self.progress = teacher or ScriptedTeacher(), progress
        self._server: threading.Thread | None = None

    def describe(self) -> dict:
        return {"type": "human", "via": "web"}

    # --- the round --------------------------------------------------------------------------------

    def label(self, pairs: SegmentPairs, rng: np.random.Generator, query: QueryRound) -> Labels:
        if pairs.physics is None:
            raise RatError("the web labeller films segments from physics states, and this run recorded none; "
                           "label it with the scripted teacher")
        self.serve()
        with LabelStore(self.store_path) as store:
            ids = store.publish(pairs, query.source, query.round, query.step, query.task, query.target)
            closed = {q["id"] for q in store.queries(query.source, open_only=False) if q["closed"]}
            if not closed & set(ids):  # else the run closed this round before it was interrupted
                self._announce(query, len(ids))
                self._film(store, ids, query.task)
                self._wait(store, ids, rng, query)
            index, y = store.close_round(query.source, query.round, query.step)
        return Labels(index, y)

    def _announce(self, query: QueryRound, n: int) -> None:
        if self.progress:
            print(f"\nquery round {query.round} (step {query.step}): {n} pairs to label at {self.config.url()}",
                  flush=True)

    def _film(self, store: LabelStore, ids: list[int], task: str) -> None:
        """Film every query of the round that has no videos yet, in order."""
        from rat.envs import LOCOMOTION_TASKS, make_task
        from rat.envs.physics import render_states
        from rat.eval import write_video

        todo = [q["id"] for q in store.queries() if q["id"] in set(ids) and q["video0"] is None]
        if not todo:
            return
        pairs = store.query_pairs(todo)
        states0, states1, scene0, scene1 = pairs.physics
        env = make_task(task, render_mode="rgb_array",
                        **({} if task in LOCOMOTION_TASKS else {"size": self.config.frame_size}))
        env.reset(seed=0)
        folder = Path("queries") / f"{ids[0]}-{ids[-1]}"
        try:
            for k, query_id in enumerate(todo):
                names = []
                for side, (states, scene) in enumerate(((states0[k], scene0[k]), (states1[k], scene1[k]))):
                    name = folder / f"{query_id}-{side}.mp4"
                    write_video(render_states(env, states, scene), self.store_path.parent / name, fps=self.config.fps)
                    names.append(name.as_posix())
                store.set_videos(query_id, *names)
        finally:
            env.close()  # its GL context goes now, not in a noisy interpreter teardown

    def _wait(self, store: LabelStore, ids: list[int], rng: np.random.Generator, query: QueryRound) -> None:
        from tqdm.auto import tqdm

        wanted, started = set(ids), time.monotonic()
        bar = tqdm(total=len(ids), desc=f"round {query.round} answered", disable=not self.progress, leave=False)
        while True:
            open_ = [q for q in store.queries(query.source) if q["id"] in wanted]
            answered = sum(q["answer"] is not None for q in open_)
            bar.update(answered - bar.n)
            if answered == len(ids):
                break
            if self.config.timeout_s is not None and time.monotonic() - started > self.config.timeout_s:
                left = [q for q in open_ if q["answer"] is None]
                self._after_timeout(store, left, rng, query)
                break
            time.sleep(self.config.poll_s)
        bar.close()

    def _after_timeout(self, store: LabelStore, left: list[dict], rng: np.random.Generator, query: QueryRound) -> None:
        """The scripted teacher answers the queries left (with ``fallback``); else they stay unanswered."""
        if self.progress:
            print(f"round {query.round}: {self.config.timeout_s:g} s passed with {len(left)} queries unanswered; "
                  + ("the scripted teacher answers them" if self.config.fallback else "they are skipped"), flush=True)
        if not self.config.fallback or not left:
            return
        ids = [q["id"] for q in left]
        labels = self.teacher.label(store.query_pairs(ids), rng, query)
        answers = {ids[i]: {0.0: "left", 1.0: "right", 0.5: "equal"}[float(y)] for i, y in zip(labels.index, labels.y)}
        for query_id in ids:
            try:
                store.answer(query_id, answers.get(query_id, "skip"), self.teacher.describe())
            except AnswerError:  # a person answered it in the meantime
                pass

    # --- the page -----------------------------------------------------------------------------------

    def serve(self) -> None:
        """Start serving the labelling page from this process (once), unless ``config.serve`` is off."""
        if not self.config.serve or self._server is not None:
            return
        from rat.labelling.server import start_server

        self._server = start_server(self.store_path, self.config)
