"""Bounded loopback load test of the registration service: ``python scripts/loadtest.py --duration 30``.

Starts ``pranet-serve`` on a free loopback port (or uses ``--url`` with the server's ``--pid``),
runs ``--clients`` concurrent clients posting ``POST /register`` for ``--duration`` seconds (at most
120; the run stops by itself), then prints the latency percentiles, the status counts, the error
count and the server's resident memory before and after (Linux /proc; workers included).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path

import httpx
import numpy as np

from pranet.core.wire import encode_cloud
from pranet.training.bench.server import served, server_settings

MAX_DURATION_S = 120.0


def rss_mib(pid: int) -> float | None:
    """Resident memory of ``pid`` and its descendants (uvicorn workers), MiB; None off Linux."""
    total_kib, todo, seen = 0, [pid], set()
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total_kib += int(line.split()[1])
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, ValueError):
            if p == pid:
                return None
    return total_kib / 1024.0


def make_body(n_points: int, steps: list[int] | None, icp: bool, encoding: str, seed: int) -> bytes:
    """A request registering an anisotropic random cloud onto a copy moved by 5° and a small shift."""
    rng = np.random.default_rng(seed)
    source = (rng.normal(size=(n_points, 3)) * [1.0, 0.5, 0.25]).astype(np.float32)
    angle = np.deg2rad(5.0)
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    target = (source @ R.T + [0.05, -0.03, 0.02]).astype(np.float32)

    def cloud(points: np.ndarray):
        if encoding == "list":
            return points.tolist()
        return encode_cloud(points)

    body: dict = {"source": cloud(source), "target": cloud(target), "icp": icp, "return_trajectory": False}
    if steps is not None:
        body["steps"] = steps
    return json.dumps(body).encode()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--url", help="a running service (default: start pranet-serve on loopback)")
    p.add_argument("--pid", type=int, help="pid of that service, for its memory (with --url)")
    p.add_argument("--api-key", help="bearer key of that service")
    p.add_argument("--clients", type=int, default=4, help="concurrent clients (default 4)")
    p.add_argument("--duration", type=float, default=30.0, help=f"seconds of load (default 30, max {MAX_DURATION_S:g})")
    p.add_argument("--points", type=int, default=2000, help="points per cloud (default 2000)")
    p.add_argument("--steps", type=int, nargs="+", help="agent steps per scale (default: the model's schedule)")
    p.add_argument("--no-icp", action="store_true", help="agent only")
    p.add_argument("--encoding", choices=["base64", "list"], default="base64")
    p.add_argument("--workers", type=int, default=1, help="workers of the started server")
    p.add_argument("--threads", type=int, default=1, help="onnxruntime threads per worker of the started server")
    p.add_argument("--max-concurrency", type=int, help="PRANET_MAX_CONCURRENCY of the started server")
    p.add_argument("--max-queue", type=int, help="PRANET_MAX_QUEUE of the started server")
    p.add_argument("--records", type=Path, help="write one JSON line per request (sent, done, status, error)")
    args = p.parse_args()
    duration = min(max(args.duration, 1.0), MAX_DURATION_S)

    with contextlib.ExitStack() as stack:
        if args.url:
            url, pid = args.url.rstrip("/"), args.pid
        else:  # the benchmark's own server: pranet-serve on loopback, SIGTERM at the end
            settings = server_settings(None, args.threads, args.workers, "fp32")
            if args.max_concurrency:
                settings["PRANET_MAX_CONCURRENCY"] = str(args.max_concurrency)
            if args.max_queue is not None:
                settings["PRANET_MAX_QUEUE"] = str(args.max_queue)
            server = stack.enter_context(served(settings, Path(stack.enter_context(tempfile.TemporaryDirectory()))))
            url, pid = server.url, server.pid
        return load(args, url, pid, duration)


@dataclass(frozen=True)
class Sample:
    """One request: when it was sent and answered (wall clock, seconds since the epoch, comparable across
    processes), its HTTP status (None: no answer) and the transport error's type, if any."""

    sent: float
    done: float
    status: int | None
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.status == 200


def run_clients(url: str, headers: dict[str, str], body: bytes, clients: int, duration: float) -> list[Sample]:
    """``clients`` threads post ``body`` to ``url``/register, each a new request as soon as the last is answered,
    until ``duration`` seconds have passed; every request sent is waited for. One ``Sample`` per request."""
    samples: list[Sample] = []
    lock = threading.Lock()
    stop_at = time.monotonic() + duration

    def client() -> None:
        with httpx.Client(base_url=url, headers=headers, timeout=60) as http:
            while time.monotonic() < stop_at:
                sent = time.time()
                try:
                    status, error = http.post("/register", content=body).status_code, None
                except httpx.HTTPError as e:
                    status, error = None, type(e).__name__
                sample = Sample(sent, time.time(), status, error)
                with lock:
                    samples.append(sample)

    threads = [threading.Thread(target=client, daemon=True) for _ in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=duration + 90)
    return sorted(samples, key=lambda s: s.sent)


def load(args: argparse.Namespace, url: str, pid: int | None, duration: float) -> int:
    """``args.clients`` clients post the same body for ``duration`` seconds; prints the counts and latencies."""
    headers = {"content-type": "application/json"}
    if args.api_key:
        headers["Authorization"] = f"Bearer {args.api_key}"
    body = make_body(args.points, args.steps, not args.no_icp, args.encoding, seed=0)

    with httpx.Client(base_url=url, headers=headers, timeout=60) as warm:  # first request pays lazy imports
        warm.post("/register", content=body)
    rss_before = rss_mib(pid) if pid else None
    started = time.monotonic()
    samples = run_clients(url, headers, body, args.clients, duration)
    elapsed = time.monotonic() - started
    rss_after = rss_mib(pid) if pid else None
    if args.records:
        args.records.write_text("".join(json.dumps(asdict(s)) + "\n" for s in samples))

    statuses = Counter(s.status for s in samples if s.status is not None)
    errors = Counter(s.error for s in samples if s.status is None)
    latencies = [s.done - s.sent for s in samples if s.ok]
    n = sum(statuses.values())
    failed = sum(1 for s in samples if not s.ok)
    print(f"server        {url}  ({args.clients} clients, {elapsed:.1f} s, {args.points} points, {args.encoding})")
    print(f"requests      {n} answered, {n / elapsed:.2f}/s; statuses {dict(sorted(statuses.items()))}")
    if latencies:
        ms = np.array(latencies) * 1e3
        p50, p95 = np.percentile(ms, [50, 95])
        print(f"latency 200   p50 {p50:.1f} ms  p95 {p95:.1f} ms  max {ms.max():.1f} ms")
    print(f"errors        {failed} (non-200 answers {failed - sum(errors.values())}, transport {dict(errors)})")
    if rss_before is not None and rss_after is not None:
        growth = rss_after - rss_before
        print(f"server RSS    before {rss_before:.1f} MiB  after {rss_after:.1f} MiB  ({growth:+.1f} MiB)")
    else:
        print("server RSS    unknown (give --pid of the server, on Linux)")
    return 0 if failed == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
