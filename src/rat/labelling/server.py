"""The labelling page and its HTTP API, served from a label store (FastAPI on uvicorn).

Routes (all JSON but the page and the videos):

- ``GET /``: the page (one HTML file with its script; no build step);
- ``GET /api/state``: the open queries whose videos are ready and that have no answer yet, and the
  progress within the open round and overall;
- ``POST /api/answers`` ``{"query_id", "choice": left|right|equal|skip, "labeller", "duration_s"}``:
  201 once the answer is durable; 404 unknown query, 409 already answered or round closed, 422
  malformed;
- ``POST /api/undo`` ``{"labeller"}``: withdraws that labeller's latest answer in an open round
  (404 when there is none);
- ``GET /videos/{query_id}/{side}``: a query's video, only from the files the store names inside
  its own directory (anything else: 404).

Off loopback every request needs the token, as ``Authorization: Bearer <token>`` or
``?token=<token>``; without it: 401. The store is the only state: each request's answer is one
SQLite transaction, so a server killed at any moment loses no acknowledged answer.
"""

# No ``from __future__ import annotations``: FastAPI reads the request bodies' models from real annotations.

import secrets
import threading
import time
from importlib import resources
from pathlib import Path

from rat.errors import RatError
from rat.labelling.web import WebLabellingConfig
from rat.preferences.store import AnswerError, LabelStore


def _require_web():
    try:
        import fastapi  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError as exc:
        raise RatError(f"the labelling page needs {exc.name}; install it with: pip install 'rat[web]'") from exc


def create_app(store_path: str | Path, token: str | None = None, wait_for_store: bool = False):
    """The labelling app serving the label store at ``store_path``; it must exist, unless
    ``wait_for_store`` (a run about to start: the page shows no queries until the run creates it)."""
    _require_web()
    from fastapi import FastAPI, HTTPException, Request
    from fastapi.responses import FileResponse, HTMLResponse, JSONResponse
    from pydantic import BaseModel, Field

    store_path = Path(store_path)
    if not wait_for_store or store_path.exists():
        LabelStore(store_path, read_only=True).close()  # exists and is a label store, or a one-line error
    local = threading.local()

    def store() -> LabelStore:
        if getattr(local, "store", None) is None:
            if not store_path.exists():  # never created here: the run creates its own store
                raise HTTPException(503, "the run has not started yet; its queries come at its first feedback round")
            local.store = LabelStore(store_path)  # one connection per server thread
        return local.store

    app = FastAPI(title="rat labelling", docs_url=None, redoc_url=None, openapi_url=None)

    if token:
        @app.middleware("http")
        async def check_token(request: Request, call_next):
            given = request.query_params.get("token") or request.headers.get("authorization", "").removeprefix("Bearer ")
            if not secrets.compare_digest(given.encode(), token.encode()):
                return JSONResponse({"detail": "this server needs its token: add ?token=... to the address"}, 401)
            return await call_next(request)

    class Answer(BaseModel):
        query_id: int
        choice: str
        labeller: str = Field("anonymous", min_length=1, max_length=64)
        duration_s: float | None = None

    class Undo(BaseModel):
        labeller: str = Field("anonymous", min_length=1, max_length=64)

    page = resources.files("rat.labelling").joinpath("static/index.html").read_text()

    def described(target: str | None) -> str | None:
        from rat.envs import get_target

        try:
            return get_target(target).description if target else None
        except RatError:  # a target this process does not know (a plugin's): its name says what it is
            return target

    @app.get("/", response_class=HTMLResponse)
    def index():
        return page

    @app.get("/api/state")
    def state():
        if not store_path.exists():
            return {"queries": [], "round": {"total": 0, "answered": 0, "filming": 0, "rounds": []},
                    "overall": {"labels": 0, "by_people": 0}}
        s = store()
        queries = s.queries(open_only=True)
        ready = [{"id": q["id"], "source": q["source"], "round": q["round"], "position": q["position"],
                  "task": q["task"], "target": q["target"], "description": described(q["target"]), "videos": [f"videos/{q['id']}/0", f"videos/{q['id']}/1"]}
                 for q in queries if q["video0"] and q["answer"] is None]
        return {"queries": ready,
                "round": {"total": len(queries), "answered": sum(q["answer"] is not None for q in queries),
                          "filming": sum(q["video0"] is None for q in queries),
                          "rounds": sorted({f"{q['source']} round {q['round']}" for q in queries})},
                "overall": {"labels": s.count(), "by_people": s.count_answered()}}

    @app.post("/api/answers", status_code=201)
    def answer(body: Answer):
        who = {"type": "human", "name": body.labeller, "via": "web"}
        try:
            label_id = store().answer(body.query_id, body.choice, who, body.duration_s)
        except AnswerError as exc:
            raise HTTPException(exc.status, str(exc)) from None
        return {"query_id": body.query_id, "label_id": label_id}

    @app.post("/api/undo")
    def undo(body: Undo):
        query_id = store().undo(body.labeller)
        if query_id is None:
            raise HTTPException(404, f"{body.labeller} has no answer in an open round to undo")
        return {"query_id": query_id}

    @app.get("/videos/{query_id}/{side}")
    def video(query_id: str, side: str):
        found = store_path.exists() and query_id.isdigit() and side in ("0", "1")
        path = store().video_path(int(query_id), int(side)) if found else None
        if path is None:
            raise HTTPException(404, "no such video")
        return FileResponse(path, media_type="video/mp4")

    return app


def _server(store_path: Path, config: WebLabellingConfig, wait_for_store: bool = False):
    import uvicorn

    app = create_app(store_path, config.token, wait_for_store)
    return uvicorn.Server(uvicorn.Config(app, host=config.host, port=config.port, log_level="warning",
                                         access_log=False))


def start_server(store_path: str | Path, config: WebLabellingConfig) -> threading.Thread:
    """Serve the page from a daemon thread of this process; returns once it accepts connections."""
    _require_web()
    server = _server(Path(store_path), config, wait_for_store=True)
    thread = threading.Thread(target=server.run, name="rat-labelling", daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RatError(f"the labelling page could not be served on {config.host}:{config.port} (is the port "
                           "taken?); choose another with --web-port")
        time.sleep(0.05)
    return thread


def serve(store_path: str | Path, config: WebLabellingConfig) -> None:
    """Serve the page in the foreground until interrupted."""
    _require_web()
    server = _server(Path(store_path), config)
    server.run()
    if not server.started:
        raise RatError(f"the labelling page could not be served on {config.host}:{config.port} (is the port taken?); "
                       "choose another with --port")
