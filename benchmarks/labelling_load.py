"""Load on the labelling server: many people answering at once, and the server killed mid-round.

    python benchmarks/labelling_load.py --clients 50 --answers 1000            # throughput and latency
    python benchmarks/labelling_load.py --clients 50 --answers 1000 --kill-at 20000

A fresh label store gets ``clients × answers`` published queries (short segments: the store's
size is not what is measured). The server runs as its own process (`rat labels serve`); every
client is a thread with its own HTTP connection that answers its own share of the queries, one
request at a time, and remembers each answer the server acknowledged (201). With
``--kill-at N`` the server is killed with SIGKILL once N answers are acknowledged, restarted, and the clients
carry on: an answer whose acknowledgement was lost with the server may be sent again and then
gets 409 (already stored). At the end the store must hold every acknowledged answer, exactly
once, and nothing else. Prints one JSON line; ``--out`` also writes it to a file.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from rat.preferences.segments import SegmentPairs
from rat.preferences.store import LabelStore

CHOICES = ("left", "right", "equal", "skip")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def make_store(path: Path, queries: int, length: int = 5) -> list[int]:
    """A store with ``queries`` published queries in one open round; returns their ids."""
    rng = np.random.default_rng(0)
    shapes = [(queries, length, 39), (queries, length, 4), (queries, length)] * 2
    pairs = SegmentPairs(*(rng.normal(size=s).astype(np.float32) for s in shapes))
    with LabelStore(path) as store:
        return store.publish(pairs, "load", round=0, step=0, task="drawer-close-v3", target="reach")


class Server:
    """``rat labels serve`` in its own process."""

    def __init__(self, store: Path, port: int):
        self.store, self.port, self.process = store, port, None

    def start(self) -> None:
        self.process = subprocess.Popen([sys.executable, "-m", "rat.cli", "labels", "serve", str(self.store), "--port",
                                         str(self.port)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.2):
                    return
            except OSError:
                if self.process.poll() is not None:
                    raise RuntimeError(f"the server exited: {self.process.stderr.read().decode()[-500:]}") from None
                time.sleep(0.05)
        raise RuntimeError("the server did not start within 60 s")

    def kill(self) -> None:
        self.process.send_signal(signal.SIGKILL)
        self.process.wait()

    def stop(self) -> None:
        self.process.terminate()
        self.process.wait(timeout=30)


def client(url: str, ids: list[int], name: str, acked: dict, latencies: list, errors: list) -> None:
    """Answer every query of ``ids`` once, retrying through a server restart."""
    import httpx

    with httpx.Client(base_url=url, timeout=30) as http:
        for k, query_id in enumerate(ids):
            body = {"query_id": query_id, "choice": CHOICES[(query_id + k) % 4], "labeller": name, "duration_s": 1.0}
            while True:
                started = time.perf_counter()
                try:
                    r = http.post("/api/answers", json=body)
                except httpx.TransportError:  # the server is down: wait for it to come back
                    time.sleep(0.1)
                    continue
                if r.status_code == 201:
                    latencies.append(time.perf_counter() - started)
                    acked[query_id] = body["choice"]
                elif r.status_code == 409 and "already answered" in r.text:
                    pass  # stored before a kill took its acknowledgement with it
                else:
                    errors.append(f"{query_id}: {r.status_code} {r.text[:200]}")
                break


def run(clients: int, answers: int, kill_at: int | None = None, folder: Path | None = None) -> dict:
    folder = Path(folder or tempfile.mkdtemp(prefix="rat-load-"))
    store = folder / "labels.sqlite"
    ids = make_store(store, clients * answers)
    server = Server(store, free_port())
    server.start()
    url = f"http://127.0.0.1:{server.port}"
    acked: dict[int, str] = {}
    latencies: list[float] = []
    errors: list[str] = []
    threads = [threading.Thread(target=client, args=(url, ids[c::clients], f"client-{c}", acked, latencies, errors))
               for c in range(clients)]
    started = time.perf_counter()
    for t in threads:
        t.start()
    killed_at = None
    if kill_at is not None:
        while len(acked) < kill_at and any(t.is_alive() for t in threads):
            time.sleep(0.001)
        killed_at = len(acked)
        server.kill()  # SIGKILL mid-round: no shutdown, no flush
        server.start()
    for t in threads:
        t.join()
    seconds = time.perf_counter() - started
    server.stop()

    with LabelStore(store, read_only=True) as s:
        stored = {q["id"]: q["answer"] for q in s.queries(open_only=False)}
        label_rows = s.db.execute("SELECT COUNT(*), COUNT(DISTINCT query_id) FROM labels").fetchone()
        skip_rows = s.db.execute("SELECT COUNT(*) FROM answers WHERE choice='skip'").fetchone()[0]
    lost = [q for q, choice in acked.items() if stored.get(q) != choice]
    unanswered = sum(a is None for a in stored.values())
    lat = np.asarray(latencies) * 1000
    return {
        "clients": clients, "answers_per_client": answers, "queries": len(ids), "seconds": round(seconds, 2),
        "acknowledged": len(acked), "answers_per_second": round(len(acked) / seconds, 1),
        "latency_ms_p50": round(float(np.percentile(lat, 50)), 2), "latency_ms_p99": round(float(np.percentile(lat, 99)), 2),
        "stored_answers": label_rows[0] + skip_rows, "duplicates": label_rows[0] - label_rows[1],
        "acknowledged_but_lost": len(lost), "unanswered": unanswered, "errors": errors[:5], "error_count": len(errors),
        "acknowledged_before_kill": killed_at,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument("--answers", type=int, default=1000, help="answers per client")
    parser.add_argument("--kill-at", type=int, default=None, help="SIGKILL the server once this many answers are acknowledged")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON result here")
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    result = run(args.clients, args.answers, args.kill_at)
    line = json.dumps(result)
    print(line)
    if args.out:
        args.out.write_text(line + "\n")


if __name__ == "__main__":
    main()
