"""A real ``pranet-serve`` on a loopback port for the HTTP rows, and its throughput under concurrent clients
(``scripts/loadtest.py`` reuses it)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pranet.training.bench.catalog import SERVER_START_TIMEOUT_S
from pranet.training.bench.tables import stats


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass(frozen=True)
class Served:
    url: str
    pid: int


@contextmanager
def served(settings: dict[str, str], log_dir: Path):
    """``pranet-serve`` (``python -m pranet.service.cli``) with ``PRANET_*`` ``settings``; yields ``Served`` (its
    URL and pid) once every worker answers /ready; SIGTERM on exit."""
    import httpx

    env = {k: v for k, v in os.environ.items() if not k.startswith("PRANET_") or k == "PRANET_DATA_DIR"}
    env.update(settings)
    port = free_port()
    log = log_dir / f"pranet-serve-{port}.log"
    cmd = [sys.executable, "-m", "pranet.service.cli", "--host", "127.0.0.1", "--port", str(port)]
    with open(log, "wb") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + SERVER_START_TIMEOUT_S
        ready = 0
        workers = int(settings.get("PRANET_WORKERS", "1"))
        while ready < 4 * workers:  # several answers in a row: every worker has loaded its model
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"pranet-serve did not come up:\n{log.read_text(errors='replace')[-3000:]}")
            try:
                ready = ready + 1 if httpx.get(f"{url}/ready", timeout=5.0).status_code == 200 else 0
            except httpx.TransportError:
                ready = 0
            time.sleep(0.05)
        yield Served(url, proc.pid)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)


def server_settings(model: str | None, threads: int, workers: int, precision: str) -> dict[str, str]:
    s = {
        "PRANET_THREADS": str(threads),
        "PRANET_WORKERS": str(workers),
        "PRANET_PRECISION": precision,
        "PRANET_LOG_LEVEL": "warning",
        "PRANET_MAX_QUEUE": "64",
    }
    if model:
        s["PRANET_MODEL_DIR"] = str(Path(model).resolve())
    return s


def throughput(url: str, bodies: Sequence[bytes], clients: int, seconds: float) -> dict[str, Any]:
    """``clients`` threads post ``bodies`` (cycled) for ``seconds``; registrations completed per second."""
    import httpx

    # Warm-up: a few requests per client (with several workers each must have run once).
    with httpx.Client(base_url=url, timeout=120.0) as c:
        for i in range(2 * clients):
            c.post("/register", content=bodies[i % len(bodies)], headers={"Content-Type": "application/json"})
    latencies: list[list[float]] = [[] for _ in range(clients)]
    errors = [0] * clients
    start = threading.Barrier(clients + 1)
    t_end = [0.0]

    def worker(k: int) -> None:
        with httpx.Client(base_url=url, timeout=120.0) as c:
            start.wait()
            i = k
            while True:
                t0 = time.perf_counter()
                if t0 >= t_end[0]:
                    return
                r = c.post("/register", content=bodies[i % len(bodies)], headers={"Content-Type": "application/json"})
                t1 = time.perf_counter()
                if t1 > t_end[0]:
                    return  # finished after the window: not counted
                if r.status_code == 200:
                    latencies[k].append((t1 - t0) * 1e3)
                else:
                    errors[k] += 1
                i += clients

    threads = [threading.Thread(target=worker, args=(k,), daemon=True) for k in range(clients)]
    for t in threads:
        t.start()
    t_end[0] = time.perf_counter() + seconds
    start.wait()
    for t in threads:
        t.join()
    done = [x for lat in latencies for x in lat]
    return {
        "clients": clients,
        "seconds": seconds,
        "completed": len(done),
        "errors": sum(errors),
        "per_s": len(done) / seconds,
        "latency_ms": stats(done),
    }
