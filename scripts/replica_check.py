"""Replicas behind nginx, on loopback, with real parts: ``python scripts/replica_check.py``.

The topology of ``deploy/compose.yaml``: ``pranet-serve`` replicas on loopback ports and Debian's nginx
(``apt-get install nginx``) with the shipped config, ``deploy/nginx/pranet.conf.template``. Clients
(``scripts/loadtest.py``'s) post registrations through nginx for ``--duration`` seconds. Runs:

  one, two  1 or 2 replicas, no signal: throughput per replica (and per core: replicas are 1-threaded);
  term      2 replicas; half-way, once two registrations are in flight on replica 0, SIGTERM it;
  kill      the same with SIGKILL.

For each run it prints the requests sent, answered (200), failed, retried by nginx (its access log), and the
latency and rate of the requests sent before and after the signal. ``--json`` writes the figures.
Exit status 1 when a SIGTERM run lost a request.
"""

from __future__ import annotations

import argparse
import json
import os
import pwd
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
from loadtest import Sample, make_body, run_clients

from pranet.core.wire import encode_cloud
from pranet.service.settings import Settings

REPO = Path(__file__).resolve().parents[1]
NGINX_TEMPLATE = REPO / "deploy" / "nginx" / "pranet.conf.template"
# One replica line of PRANET_UPSTREAM_SERVERS; deploy/compose.yaml uses the same parameters (a test checks).
UPSTREAM_SERVER = "server {address} max_fails=1 fail_timeout=2s;"
RUNS = {"one": (1, None), "two": (2, None), "term": (2, signal.SIGTERM), "kill": (2, signal.SIGKILL)}
# Each replica as a pod of deploy/k8s: one core, so one uvicorn worker, one thread for onnxruntime, OpenMP (Open3D's
# ICP) and BLAS, one registration at a time (the others wait in its queue, PRANET_MAX_QUEUE, default 4).
REPLICA_ENV = {
    "PRANET_THREADS": "1",
    "PRANET_WORKERS": "1",
    "PRANET_MAX_CONCURRENCY": "1",
    "PRANET_LOG_LEVEL": "warning",
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OMP_WAIT_POLICY": "PASSIVE",
}
START_TIMEOUT_S = 120.0
# The replica is signalled once this many registrations are in flight on it (one computing, one queued): one of
# them is still in flight when the signal lands, even if another finishes in between.
IN_FLIGHT_AT_SIGNAL = 2
IN_FLIGHT_WAIT_S = 20.0


def pair_body(source: Path, target: Path) -> bytes:
    """The default request for two cloud files, base64-encoded as pranet-client sends them."""
    from pranet.client.io import read_point_cloud

    clouds = {name: encode_cloud(read_point_cloud(path)) for name, path in (("source", source), ("target", target))}
    return json.dumps({**clouds, "return_trajectory": False}).encode()


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def render_template(text: str, values: Mapping[str, str]) -> str:
    """Each ``${PRANET_...}`` -> its value, as envsubst does in the nginx image (NGINX_ENVSUBST_FILTER=^PRANET_);
    every one must be given."""
    rendered = re.sub(r"\$\{(PRANET_\w+)\}", lambda m: values.get(m.group(1), m.group(0)), text)
    missing = sorted(set(re.findall(r"\$\{(PRANET_\w+)\}", rendered)))
    if missing:
        raise ValueError(f"no value for {', '.join(missing)} in {NGINX_TEMPLATE.name}")
    return rendered


def nginx_binary() -> str:
    found = shutil.which("nginx") or next((p for p in ("/usr/sbin/nginx",) if os.access(p, os.X_OK)), None)
    if found is None:
        raise SystemExit("nginx not found: install Debian's package (apt-get install -y nginx)")
    return found


# --- the parts: replicas and nginx ------------------------------------------------------------------------


@dataclass
class Replica:
    name: str
    port: int
    process: subprocess.Popen
    log: Path

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.port}"

    def in_flight(self) -> int:
        return int(httpx.get(f"{self.url}/ready", timeout=5).json()["in_flight"])


def start_replica(name: str, work: Path) -> Replica:
    """``pranet-serve`` on a free loopback port (not yet waited for: see ``wait_ready``)."""
    port = free_port()
    log = work / f"{name}.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PRANET_")} | REPLICA_ENV
    serve = Path(sys.executable).parent / "pranet-serve"
    cmd = [str(serve) if serve.exists() else "pranet-serve", "--host", "127.0.0.1", "--port", str(port)]
    with open(log, "wb") as out:
        process = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env)
    return Replica(name, port, process, log)


def wait_ready(replica: Replica, body: bytes) -> None:
    """Until /ready answers 200, then one registration straight to it: its first one pays the lazy imports."""
    deadline = time.monotonic() + START_TIMEOUT_S
    while True:
        if replica.process.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"{replica.name} did not come up:\n{replica.log.read_text(errors='replace')[-3000:]}")
        try:
            if httpx.get(f"{replica.url}/ready", timeout=2).status_code == 200:
                break
        except httpx.TransportError:
            pass
        time.sleep(0.1)
    headers = {"content-type": "application/json"}
    httpx.post(f"{replica.url}/register", content=body, headers=headers, timeout=60).raise_for_status()


def stop_replica(replica: Replica) -> None:
    if replica.process.poll() is None:
        replica.process.send_signal(signal.SIGTERM)
        try:
            replica.process.wait(timeout=Settings().shutdown_timeout_s + 10)
        except subprocess.TimeoutExpired:
            replica.process.kill()
            replica.process.wait(timeout=10)


@contextmanager
def replicas_up(count: int, work: Path, body: bytes) -> Iterator[list[Replica]]:
    """``count`` replicas, started together, each ready and warm; stopped (SIGTERM) on exit."""
    started: list[Replica] = []
    try:
        for i in range(count):
            started.append(start_replica(f"replica{i}", work))
        for replica in started:
            wait_ready(replica, body)
        yield started
    finally:
        for replica in started:
            stop_replica(replica)


def nginx_config(work: Path, listen: str, upstreams: Sequence[str]) -> Path:
    """The main nginx.conf for a process of our own (pid, logs, temp files in ``work``) that includes the
    shipped template rendered for ``upstreams``; returns its path."""
    servers = "\n    ".join(UPSTREAM_SERVER.format(address=a) for a in upstreams)
    values = {
        "PRANET_LISTEN": listen,
        "PRANET_UPSTREAM_SERVERS": servers,
        "PRANET_MAX_BODY_BYTES": str(Settings().body_limit_bytes),
    }
    (work / "pranet.conf").write_text(render_template(NGINX_TEMPLATE.read_text(), values))
    temp = {k: work / k for k in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi")}
    main = f"""
daemon off;
worker_processes 1;
# Workers run as this process's user (root's default would be nobody), so that they can use the temp folders
# below; nginx ignores it, with a warning, when not started as root.
user {pwd.getpwuid(os.geteuid()).pw_name};
pid {work}/nginx.pid;
error_log {work}/nginx-error.log warn;
events {{ worker_connections 512; }}
http {{
    client_body_temp_path {temp["client_body"]};
    proxy_temp_path {temp["proxy"]};
    fastcgi_temp_path {temp["fastcgi"]};
    uwsgi_temp_path {temp["uwsgi"]};
    scgi_temp_path {temp["scgi"]};
    include {work}/pranet.conf;
}}
"""
    path = work / "nginx.conf"
    path.write_text(main)
    return path


@dataclass
class Nginx:
    url: str
    process: subprocess.Popen
    access_log: Path


@contextmanager
def nginx_up(work: Path, upstreams: Sequence[str]) -> Iterator[Nginx]:
    """Debian's nginx on a free loopback port in front of ``upstreams``, once it answers (/health, through it: 200
    once a replica is up, its own 503 when none is)."""
    port = free_port()
    conf = nginx_config(work, f"127.0.0.1:{port}", upstreams)
    access_log = work / "nginx-access.log"  # the template logs to /dev/stdout
    binary = nginx_binary()
    check = subprocess.run(
        [binary, "-t", "-q", "-p", str(work), "-c", str(conf), "-e", str(work / "nginx-error.log")],
        capture_output=True,
        text=True,
    )
    if check.returncode != 0:
        raise RuntimeError(f"nginx -t refused the config:\n{check.stderr}")
    with open(access_log, "wb") as out:
        process = subprocess.Popen(
            [binary, "-p", str(work), "-c", str(conf), "-e", str(work / "nginx-error.log")],
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    nginx = Nginx(f"http://127.0.0.1:{port}", process, access_log)
    try:
        deadline = time.monotonic() + 30
        while True:
            if process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"nginx did not come up:\n{(work / 'nginx-error.log').read_text()[-2000:]}")
            try:
                httpx.get(f"{nginx.url}/health", timeout=5)
                break
            except httpx.TransportError:
                pass
            time.sleep(0.05)
        yield nginx
    finally:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


# --- one run -------------------------------------------------------------------------------------------------

LOG_LINE = re.compile(
    r'\] (\S+) "POST /register [^"]*" (\d+) \S+ (\S+) upstream=(.*) upstream_status=(.*) upstream_time='
)
# Why nginx gave up on a try (its error log): the replica was gone, or it went away with the request.
TRY_FAILURES = {
    "refused": ("Connection refused",),
    "cut": ("prematurely closed", "reset by peer", "Broken pipe"),
    "timed out": ("timed out",),
}


def try_failure(error_line: str) -> str | None:
    """The kind of failed try an nginx error-log line reports (a ``TRY_FAILURES`` key), if it reports one."""
    if "[error]" not in error_line or "upstream" not in error_line:  # [warn]: "upstream server temporarily disabled"
        return None
    return next((kind for kind, marks in TRY_FAILURES.items() if any(m in error_line for m in marks)), "other")


def nginx_counts(work: Path, names: Mapping[str, str], signal_at: float | None) -> dict:
    """From nginx's logs: the registrations it answered, those it retried on another replica (and why the failed
    tries failed), and how many each replica answered (the last try), in all and after ``signal_at``."""
    log = (work / "nginx-access.log").read_text(errors="replace").splitlines()
    answered_by: Counter = Counter()
    after_signal: Counter = Counter()
    retried_s: list[float] = []
    for end, _status, seconds, addresses, _statuses in (m.groups() for m in map(LOG_LINE.search, log) if m):
        last = names.get(addresses.split(",")[-1].strip(), addresses)
        answered_by[last] += 1
        if signal_at is not None and float(end) > signal_at:
            after_signal[last] += 1
        if "," in addresses:
            retried_s.append(float(seconds))
    errors = (work / "nginx-error.log").read_text(errors="replace").splitlines()
    failures = Counter(kind for kind in map(try_failure, errors) if kind)
    return {
        "requests": sum(answered_by.values()),
        "retried": len(retried_s),
        "retried_max_s": max(retried_s, default=0.0),
        "failed_tries": dict(failures),
        "answered_by": dict(answered_by),
        "answered_after_signal_by": dict(after_signal),
    }


def window(samples: Sequence[Sample]) -> dict:
    """Counts, rate and latency of ``samples`` (requests sent in one window)."""
    ok = [s.done - s.sent for s in samples if s.ok]
    span = (max(s.done for s in samples) - min(s.sent for s in samples)) if samples else 0.0
    p50, p95 = np.percentile(np.array(ok) * 1e3, [50, 95]) if ok else (float("nan"),) * 2
    return {
        "sent": len(samples),
        "answered": len(ok),
        "failed": len(samples) - len(ok),
        "per_s": len(ok) / span if span else 0.0,
        "p50_ms": float(p50),
        "p95_ms": float(p95),
    }


def cpu_seconds(pid: int) -> float:
    """User + system CPU time so far of process ``pid`` and its children (nginx's workers), from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    own = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    children = [int(c) for task in Path(f"/proc/{pid}/task").iterdir() for c in (task / "children").read_text().split()]
    return own + sum(cpu_seconds(c) for c in children)


def signal_when_busy(replica: Replica, sig: signal.Signals, at: float) -> dict:
    """At wall time ``at``, and once ``IN_FLIGHT_AT_SIGNAL`` registrations are in flight on ``replica`` (or after
    ``IN_FLIGHT_WAIT_S``), send it ``sig``; then wait for it to exit. What happened, for the report."""
    time.sleep(max(0.0, at - time.time()))
    deadline = time.monotonic() + IN_FLIGHT_WAIT_S
    in_flight = 0
    while time.monotonic() < deadline and (in_flight := replica.in_flight()) < IN_FLIGHT_AT_SIGNAL:
        time.sleep(0.02)
    sent_at = time.time()
    replica.process.send_signal(sig)
    code = replica.process.wait(timeout=Settings().shutdown_timeout_s + 10)
    return {"signal": sig.name, "at": sent_at, "in_flight": in_flight, "exit_s": time.time() - sent_at, "exit": code}


def load_and_signal(
    nginx: Nginx, replicas: Sequence[Replica], sig: signal.Signals | None, clients: int, duration: float, body: bytes
) -> tuple[list[Sample], dict]:
    """The clients through nginx for ``duration`` seconds; half-way, ``sig`` to replica 0 (if any). Returns the
    samples and what the signal did."""
    headers = {"content-type": "application/json"}
    with ThreadPoolExecutor(1) as pool:
        started = time.time()
        signalled = pool.submit(signal_when_busy, replicas[0], sig, started + duration / 2) if sig else None
        samples = run_clients(nginx.url, headers, body, clients, duration)
        events = signalled.result() if signalled else {}
    if events:
        events["at_s"] = events["at"] - started
    return samples, events


def cpu_per_registration(pids: Sequence[int], cpu_before: Sequence[float], answered: int) -> dict:
    """CPU time, not wall time: what a registration costs, whatever else shares the cores. The last pid is nginx."""
    used = [cpu_seconds(pid) - before for pid, before in zip(pids, cpu_before, strict=True)]
    replicas_s = sum(used[:-1])
    return {
        "replicas_s": replicas_s,
        "per_cpu_s": answered / replicas_s if replicas_s else 0.0,
        "nginx_s": used[-1],
    }


def one_run(name: str, duration: float, clients: int, body: bytes) -> dict:
    """One run of ``RUNS``: its own replicas and nginx, the load, the signal; the figures."""
    count, sig = RUNS[name]
    with ExitStack() as stack:
        work = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix=f"replica-check-{name}-")))
        replicas = stack.enter_context(replicas_up(count, work, body))
        nginx = stack.enter_context(nginx_up(work, [r.address for r in replicas]))
        pids = [r.process.pid for r in replicas] + [nginx.process.pid]
        cpu_before = [cpu_seconds(pid) for pid in pids]
        samples, events = load_and_signal(nginx, replicas, sig, clients, duration, body)
        result = {
            "run": name,
            "replicas": count,
            "clients": clients,
            "duration_s": duration,
            "all": window(samples),
            "statuses": dict(Counter(str(s.status) for s in samples)),
            "errors": dict(Counter(s.error for s in samples if s.error)),
        }
        if sig is None:  # a signalled replica's CPU time is gone with it
            result["cpu"] = cpu_per_registration(pids, cpu_before, result["all"]["answered"])
        time.sleep(0.2)  # nginx writes its access log line after the answer
        result["nginx"] = nginx_counts(work, {r.address: r.name for r in replicas}, events.get("at"))
        if events:
            result["signal"] = events
            result["before"] = window([s for s in samples if s.sent < events["at"]])
            result["after"] = window([s for s in samples if s.sent >= events["at"]])
        return result


# --- the table ---------------------------------------------------------------------------------------------


def cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def latency(w: dict) -> str:
    return f"{w['p50_ms']:.0f} / {w['p95_ms']:.0f}"


def print_table(results: Sequence[dict], what: str) -> None:
    print(f"replicas behind nginx: {what}, base64, the default request; {cores()} cores here")
    print()
    print("| run | replicas | clients | sent | answered | failed | retried by nginx | answered by | answered/s |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: |")
    for r in results:
        by = ", ".join(f"{k} {v}" for k, v in sorted(r["nginx"]["answered_by"].items()))
        n = r["nginx"]
        reasons = ", ".join(f"{k} {v}" for k, v in sorted(n["failed_tries"].items()))
        retried = f"{n['retried']} (tries {reasons}; slowest {n['retried_max_s']:.1f} s)" if n["retried"] else "0"
        a = r["all"]
        print(
            f"| {r['run']} | {r['replicas']} | {r['clients']} | {a['sent']} | {a['answered']} | {a['failed']} "
            f"| {retried} | {by} | {a['per_s']:.2f} |"
        )
    signalled = [r for r in results if "signal" in r]
    if signalled:
        print()
        print(
            "| run | in flight on replica0 at the signal | answered by replica0 after it | replica0 exited after "
            "| before: sent / answered | p50 / p95 ms | answered/s | after: sent / answered | p50 / p95 ms "
            "| answered/s |"
        )
        print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
        for r in signalled:
            s, b, a = r["signal"], r["before"], r["after"]
            finished = r["nginx"]["answered_after_signal_by"].get("replica0", 0)
            print(
                f"| {r['run']} ({s['signal']} at {s['at_s']:.1f} s) | {s['in_flight']} | {finished} "
                f"| {s['exit_s']:.2f} s "
                f"| {b['sent']} / {b['answered']} | {latency(b)} | {b['per_s']:.2f} "
                f"| {a['sent']} / {a['answered']} | {latency(a)} | {a['per_s']:.2f} |"
            )
    plain = [r for r in results if "cpu" in r]
    if plain:
        print()
        print(
            "| run | replicas | answered/s (wall, cores shared) | registrations per CPU-second | nginx CPU, whole run |"
        )
        print("| --- | ---: | ---: | ---: | ---: |")
        for r in plain:
            c = r["cpu"]
            print(
                f"| {r['run']} | {r['replicas']} | {r['all']['per_s']:.2f} | {c['per_cpu_s']:.2f} "
                f"| {c['nginx_s']:.2f} s |"
            )
        rates = {n: [r["all"]["per_s"] for r in plain if r["run"] == n] for n in ("one", "two")}
        per_cpu = float(np.median([r["cpu"]["per_cpu_s"] for r in plain]))
        print()
        print(
            f"per core: {per_cpu:.2f} registrations per CPU-second of the replicas, {1e3 / per_cpu:.0f} ms of CPU each "
            "(median of the runs above): what a replica answers per second on a core of its own. A replica uses a "
            "little more than its one compute thread: its event loop reads the next request meanwhile."
        )
        if all(rates.values()):
            ratio = float(np.median(rates["two"]) / np.median(rates["one"]))
            print(
                f"2 replicas / 1 replica, wall-clock answered/s (medians): x{ratio:.2f} "
                f"(x2 at best, with a core each; {cores()} cores here, shared with whatever else runs)"
            )


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", default="term,kill", help=f"comma-separated, of {', '.join(RUNS)} (default term,kill)")
    p.add_argument("--duration", type=float, default=20.0, help="seconds of load per run (default 20)")
    p.add_argument("--clients", type=int, default=4, help="concurrent clients (default 4)")
    p.add_argument("--points", type=int, default=2000, help="points per synthetic cloud (default 2000)")
    p.add_argument(
        "--pair",
        nargs=2,
        type=Path,
        metavar=("SOURCE", "TARGET"),
        help="register these two cloud files instead (e.g. examples/bunny/bun045.ply examples/bunny/bun000.ply)",
    )
    p.add_argument("--json", type=Path, help="write the figures here")
    args = p.parse_args(argv)
    runs = [r.strip() for r in args.runs.split(",") if r.strip()]
    unknown = [r for r in runs if r not in RUNS]
    if unknown:
        p.error(f"unknown run(s) {', '.join(unknown)}: choose from {', '.join(RUNS)}")
    nginx_binary()
    body = pair_body(*args.pair) if args.pair else make_body(args.points, None, True, "base64", seed=0)
    what = " -> ".join(str(p) for p in args.pair) if args.pair else f"synthetic, {args.points} points per cloud"
    results = [one_run(name, args.duration, args.clients, body) for name in runs]
    print_table(results, what)
    if args.json:
        args.json.write_text(json.dumps({"body": what, "cores": cores(), "runs": results}, indent=1))
    lost = [r["run"] for r in results if r.get("signal", {}).get("signal") == "SIGTERM" and r["all"]["failed"]]
    if lost:
        print(f"requests lost with SIGTERM in run(s) {', '.join(lost)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
