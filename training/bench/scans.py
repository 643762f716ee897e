"""``pranet-bench scans PAIRS.csv``: PRANet's default request against classical peers on real scan pairs.

Every pair of the CSV (``training.bench.scan_pairs`` describes the format and the right/wrong rule) is
registered by every method in one run, the methods' order rotated pair by pair so that a busy machine slows all
of them alike. Both clouds are read once and rounded to float32 (what the HTTP client sends). Per pair: the
voxel (4x the source's median point spacing, ``scan_peers.scan_voxel``), and per method the rotation and
translation errors, the latency, right or wrong, and where the method says so its status, confidence and the
candidate that won.

Methods:

- ``pranet``: ``Engine.register(source, target)`` in process with the service's default configuration
  (``SERVICE_DEFAULT``), seed ``--seed``; in process there is no point limit;
- ``pranet-http``: the same default request (the two clouds, nothing else) to a real ``pranet-serve`` on a
  loopback port, client-side latency; the server's own point limit applies;
- ``open3d-ransac-icp``, ``kiss-matcher-gicp``, ``fgr-icp``: the classical peers of ``scan_peers``, at the same
  voxel (its measurement is part of each peer's latency: a user must measure it too).

Examples::

    pranet-bench scans                                 # $PRANET_DATA_DIR/scans/pairs.csv (../shared/data)
    pranet-bench scans pairs.csv --methods pranet,kiss-matcher-gicp --pairs-limit 3 --out results/scans.json
    pranet-bench scans ../shared/data/scans/pairs.csv --doc docs/PERFORMANCE.md   # rewrite its "Real scans"
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shlex
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pranet.core.se3 import Array
from pranet.training.bench.scan_pairs import (
    DEFAULT_THRESHOLDS,
    ScanPair,
    Thresholds,
    is_right,
    parse_thresholds,
    pose_errors,
    read_pairs,
)
from pranet.training.bench.scan_peers import PEERS, scan_voxel

PRANET_METHODS = ("pranet", "pranet-http")
METHODS = (*PRANET_METHODS, *PEERS)
DEFAULT_METHODS = ("pranet", *PEERS)


@dataclass
class LoadedPair:
    pair: ScanPair
    source: Array  # (N, 3) float64 holding float32 values
    target: Array
    voxel: float


@dataclass
class Answer:
    """What a method returns for one pair: the estimate, and what it says of it (PRANet only)."""

    transform: Array
    status: str | None = None
    confidence: float | None = None
    candidate: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)


ScanMethod = Callable[[LoadedPair, int], Answer]


@dataclass
class ScanRecord:
    pair: str
    category: str  # "object" | "scene": which thresholds judged it
    method: str
    ms: float
    rotation_deg: float
    translation: float
    right: bool
    status: str | None = None
    confidence: float | None = None
    candidate: str | None = None
    error: str | None = None
    transform: list[list[float]] | None = None
    extra: dict[str, Any] = field(default_factory=dict)


# --- arguments ----------------------------------------------------------------------------------------------


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="pranet-bench scans",
        description=(__doc__ or "").split("\n\n")[0],
        epilog="Right: within 2° and 3 mm for pairs whose kind says 'object', else 15° and 30 cm (units: metres).",
    )
    p.add_argument(
        "pairs_csv",
        type=Path,
        nargs="?",
        default=None,
        help="the pairs file (the format of shared/data/scans/pairs.csv; default: scans/pairs.csv under the data "
        "root, $PRANET_DATA_DIR or ../shared/data)",
    )
    p.add_argument("--methods", default=",".join(DEFAULT_METHODS), help=f"subset of {','.join(METHODS)}")
    p.add_argument("--pairs-limit", type=int, default=None, help="only the first N pairs of the file")
    p.add_argument("--thresholds", action="append", default=[], metavar="[object=|scene=]ROT_DEG,TRANS",
                   help="override the right/wrong thresholds (every pair, or one category); repeatable")  # fmt: skip
    p.add_argument("--seed", type=int, default=0, help="the request's seed and the peers' RANSAC seed (default 0)")
    p.add_argument("--threads", type=int, default=2, help="threads per method (default 2)")
    p.add_argument("--model", default=None, help="model directory (default: the shipped model)")
    p.add_argument("--out", type=Path, default=None, help="write every record and the summary here (JSON)")
    p.add_argument("--markdown", type=Path, default=None, help="write the tables (with the command) here")
    p.add_argument("--doc", type=Path, default=None, help='rewrite the "Real scans" section of this markdown file')
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    args = p.parse_args(argv)
    if args.pairs_csv is None:
        from pranet.training.data import data_dir

        args.pairs_csv = data_dir() / "scans" / "pairs.csv"
    chosen = [m.strip() for m in args.methods.split(",") if m.strip()]
    if not chosen or any(m not in METHODS for m in chosen):
        p.error(f"--methods from {','.join(METHODS)}")
    args.methods = [m for m in METHODS if m in chosen]
    try:
        args.thresholds = parse_thresholds(args.thresholds)
    except ValueError as e:
        p.error(str(e))
    if args.pairs_limit is not None and args.pairs_limit < 1:
        p.error("--pairs-limit must be at least 1")
    return args


def log(args: argparse.Namespace, msg: str) -> None:
    if not args.quiet:
        print(f"pranet-bench scans: {msg}", file=sys.stderr, flush=True)


# --- the pairs and the methods ------------------------------------------------------------------------------


def load_pair(pair: ScanPair, seed: int) -> LoadedPair:
    from pranet.client.io import read_point_cloud

    source = read_point_cloud(pair.source).astype(np.float32).astype(np.float64)
    target = read_point_cloud(pair.target).astype(np.float32).astype(np.float64)
    return LoadedPair(pair, source, target, scan_voxel(source, seed))


def winning_candidate(reg: Any) -> str:
    """Which candidate the pipeline returned: its own field when it has one, else the rescue that won, else the
    agent."""
    return getattr(reg, "candidate", None) or getattr(reg, "rescued", None) or "agent"


def pranet_method(engine: Any) -> ScanMethod:
    """The service's default request, in process."""
    from pranet.core.registration_config import SERVICE_DEFAULT

    def run(lp: LoadedPair, seed: int) -> Answer:
        reg = engine.register(lp.source, lp.target, SERVICE_DEFAULT, seed, seed=seed)  # as the service
        conf = reg.confidence
        return Answer(
            reg.T_target_source,
            conf.status if conf is not None else None,
            conf.score if conf is not None else None,
            winning_candidate(reg),
            {"timing_ms": dict(reg.timing_ms), "network_calls": reg.network_calls},
        )

    return run


def http_method(client: Any) -> ScanMethod:
    """The default request over HTTP: the two clouds (base64 float32, as ``pranet-client`` sends them) and the
    seed, every option left to the service."""
    from pranet.core.wire import encode_cloud

    def run(lp: LoadedPair, seed: int) -> Answer:
        body = {"source": encode_cloud(lp.source), "target": encode_cloud(lp.target), "seed": seed}
        r = client.post("/register", content=json.dumps(body), headers={"Content-Type": "application/json"})
        if r.status_code != 200:
            raise RuntimeError(f"HTTP {r.status_code}: {r.text[:200]}")
        data = r.json()
        candidate = data.get("candidate") or data.get("rescued") or "agent"
        extra = {"server_timing_ms": data.get("timing_ms", {}), "network_calls": data.get("network_calls")}
        return Answer(
            np.asarray(data["transform"], dtype=np.float64), data["status"], data["confidence"], candidate, extra
        )

    return run


def peer_method(name: str, threads: int) -> ScanMethod:
    """A classical peer; it measures the voxel itself (the same value ``load_pair`` measured)."""
    fn = PEERS[name]

    def run(lp: LoadedPair, seed: int) -> Answer:
        return Answer(fn(lp.source, lp.target, scan_voxel(lp.source, seed), seed, threads))

    return run


def timed(fn: ScanMethod, lp: LoadedPair, seed: int) -> tuple[Answer | None, float, str | None]:
    t0 = time.perf_counter()
    try:
        answer, error = fn(lp, seed), None
    except Exception as e:  # a refusal or a crash is a wrong answer, reported
        answer, error = None, f"{type(e).__name__}: {e}"
    return answer, (time.perf_counter() - t0) * 1e3, error


def score(method: str, lp: LoadedPair, answer: Answer | None, ms: float, error: str | None, limits: Thresholds):
    pair = lp.pair
    if answer is None:
        return ScanRecord(pair.id, pair.category, method, ms, float("nan"), float("nan"), False, error=error)
    rot, trans = pose_errors(answer.transform, pair.T_gt)
    return ScanRecord(
        pair.id,
        pair.category,
        method,
        ms,
        rot,
        trans,
        is_right(rot, trans, limits),
        answer.status,
        answer.confidence,
        answer.candidate,
        None,
        np.asarray(answer.transform).tolist(),
        answer.extra,
    )


# --- the run ------------------------------------------------------------------------------------------------


def build_methods(args: argparse.Namespace, engine: Any, client: Any) -> dict[str, ScanMethod]:
    fns: dict[str, ScanMethod] = {}
    for m in args.methods:
        if m == "pranet":
            fns[m] = pranet_method(engine)
        elif m == "pranet-http":
            fns[m] = http_method(client)
        else:
            fns[m] = peer_method(m, args.threads)
    return fns


def run_interleaved(
    args: argparse.Namespace, pairs: list[ScanPair], fns: dict[str, ScanMethod], t_start: float
) -> tuple[list[ScanRecord], list[dict[str, Any]]]:
    """Every method on every pair, their order rotated per pair; one warm-up call each on the first pair."""
    records: list[ScanRecord] = []
    pair_rows: list[dict[str, Any]] = []
    order = list(fns)
    for i, pair in enumerate(pairs):
        lp = load_pair(pair, args.seed)
        pair_rows.append(
            {
                "id": pair.id,
                "kind": pair.kind,
                "category": pair.category,
                "n_source": len(lp.source),
                "n_target": len(lp.target),
                "voxel": lp.voxel,
                "rotation_deg": pair.rotation_deg,
                "overlap": pair.overlap,
                "thresholds": asdict(args.thresholds[pair.category]),
            }
        )
        if i == 0:
            for m in order:  # first calls: imports, allocations, connections
                timed(fns[m], lp, args.seed)
        k = i % len(order)
        for m in order[k:] + order[:k]:
            answer, ms, error = timed(fns[m], lp, args.seed)
            records.append(score(m, lp, answer, ms, error, args.thresholds[pair.category]))
        done = ", ".join(f"{r.method} {'ok' if r.right else 'WRONG'} {r.ms:.0f} ms" for r in records[-len(order) :])
        log(args, f"{i + 1}/{len(pairs)} {pair.id}: {done} ({time.perf_counter() - t_start:.0f} s)")
    return records, pair_rows


def _version(dist: str) -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
    except PackageNotFoundError:
        return None


def run(args: argparse.Namespace, command: str) -> dict[str, Any]:
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))  # Open3D reads it at import
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # busy-waiting OpenMP threads collapse on a shared core
    from pranet.training.bench.scan_report import summarize
    from pranet.training.reporting import environment

    t_start = time.perf_counter()
    pairs = read_pairs(args.pairs_csv)[: args.pairs_limit]
    result: dict[str, Any] = {"command": command, "environment": environment(args.threads)}
    result["environment"]["kiss_matcher"] = _version("kiss_matcher")
    result["config"] = {
        "pairs_csv": str(args.pairs_csv),
        "methods": args.methods,
        "seed": args.seed,
        "threads": args.threads,
        "model": args.model,
        "thresholds": {k: asdict(v) for k, v in args.thresholds.items()},
        "default_thresholds": {k: asdict(v) for k, v in DEFAULT_THRESHOLDS.items()},
    }
    engine = None
    if "pranet" in args.methods:
        from pranet.engine.engine import Engine

        engine = Engine.load(args.model, threads=args.threads)
        result["model"] = engine.scorer.info()
    with maybe_served(args) as client:
        fns = build_methods(args, engine, client)
        records, result["pairs"] = run_interleaved(args, pairs, fns, t_start)
    result["summary"] = summarize(records, args.methods)
    result["records"] = [asdict(r) for r in records]
    result["wall_s"] = time.perf_counter() - t_start
    return result


@contextlib.contextmanager
def maybe_served(args: argparse.Namespace) -> Iterator[Any]:
    """An HTTP client on a real ``pranet-serve`` (one worker, ``--threads``) when ``pranet-http`` is asked for,
    else ``None``."""
    if "pranet-http" not in args.methods:
        yield None
        return
    import httpx

    from pranet.training.bench.server import served, server_settings

    with tempfile.TemporaryDirectory(prefix="pranet-bench-scans-") as tmp:
        with served(server_settings(args.model, args.threads, 1, "fp32"), Path(tmp)) as server:
            with httpx.Client(base_url=server.url, timeout=600.0) as client:
                yield client


def main(argv: Sequence[str] | None = None) -> int:
    from pranet.training.bench.scan_report import report, write_doc_section
    from pranet.training.reporting import json_default, nan_to_none

    argv = list(sys.argv[2:] if argv is None else argv)  # after "pranet-bench scans"
    args = parse_args(argv)
    command = shlex.join(["pranet-bench", "scans", *argv])
    try:
        result = run(args, command)
    except ValueError as e:  # a malformed pairs file or cloud: one line, no traceback
        print(f"pranet-bench scans: error: {e}", file=sys.stderr)
        return 2
    text = report(result)
    print(text)
    if args.markdown is not None:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(f"```\n{command}\n```\n\n{text}\n")
        log(args, f"wrote {args.markdown}")
    if args.doc is not None:
        write_doc_section(args.doc, command, text)
        log(args, f"rewrote the Real scans section of {args.doc}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(nan_to_none(json.loads(json.dumps(result, default=json_default))), indent=1))
        log(args, f"wrote {args.out}")
    return 0
