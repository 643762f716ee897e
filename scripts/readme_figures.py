"""The README's figures on the shipped example pair, measured over HTTP as a new user meets them.

    python scripts/readme_figures.py [--url http://127.0.0.1:8000] [--repeats 5] [--scans PAIRS.csv | none]

Without ``--url`` it starts its own ``pranet-serve`` (the shipped model, ``PRANET_THREADS=1``) on a free
loopback port and stops it at the end. The pair is ``examples/bunny`` (source ``bun045``, target ``bun000``,
ground truth ``T_target_source.txt``). Every request is what ``pranet-client register`` sends, plus the one
option named on its line. It prints the lines the README quotes; rerun it after any change to the pipeline,
the confidence or the model, and paste them (the README names this command beside them). When the real scans
are there (``../shared/data/scans/pairs.csv``, or ``--scans``), it then registers every pair of them with the
default request and says which candidates ran and which won.

Latencies are client-side wall times of interleaved requests (medians), so the two requests of a ratio see the
same machine load; absolute milliseconds depend on the machine, the ratio much less.
"""

from __future__ import annotations

import argparse
import csv
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from pathlib import Path

import numpy as np

from pranet.client import PranetClient, PranetError
from pranet.client.client import RegistrationResult
from pranet.client.io import read_point_cloud
from pranet.core.metrics import isotropic_errors
from pranet.training.data import data_dir

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "bunny"
OFF_DEG = 10.0  # the "slightly wrong pose" whose confidence the README quotes
NO_RESCUE = 'with "rescue": false'


@contextmanager
def own_service() -> Iterator[str]:
    """A ``pranet-serve`` of this interpreter's environment on a free port, with one onnxruntime thread."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    serve = Path(sys.executable).parent / "pranet-serve"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PRANET_")}
    env.update(PRANET_THREADS="1", PRANET_LOG_LEVEL="warning")
    process = subprocess.Popen([str(serve), "--host", "127.0.0.1", "--port", str(port)], env=env)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        process.send_signal(signal.SIGTERM)
        process.wait(timeout=60)


def _figure(x: float) -> str:
    """Two or three significant figures: 0.58, 6.0, 14.3, 694."""
    return f"{x:.2f}" if x < 1 else f"{x:.1f}" if x < 100 else f"{x:.0f}"


def fmt_errors(T: np.ndarray, T_true: np.ndarray) -> str:
    """Rotation and translation error of ``T`` against the truth, in degrees and millimetres (the clouds: metres)."""
    rot, trans = isotropic_errors(T, T_true)
    return f"{_figure(rot)}° / {_figure(trans * 1e3)} mm"


def timed(client: PranetClient, source: np.ndarray, target: np.ndarray, **options) -> tuple[RegistrationResult, float]:
    t0 = time.perf_counter()
    result = client.register(source, target, **options)
    return result, (time.perf_counter() - t0) * 1e3


def rotated_about_centroid(T: np.ndarray, degrees: float, axis: int, centre: np.ndarray) -> np.ndarray:
    """``T`` followed by a rotation of ``degrees`` about coordinate axis ``axis`` through ``centre``."""
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    i, j = [k for k in range(3) if k != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    off = np.eye(4)
    off[:3, :3], off[:3, 3] = R, centre - R @ centre
    return off @ T


def confidence_of_pose(client: PranetClient, source: np.ndarray, target: np.ndarray, T: np.ndarray) -> str:
    """The service's confidence in pose ``T`` itself: the source moved by ``T``, then no agent step and no ICP."""
    moved = source @ T[:3, :3].T + T[:3, 3]
    options = {"icp": False, "steps": [0, 0], "exit_checks": [], "rescue": False, "return_trajectory": False}
    try:
        result = client.register(moved, target, **options)
    except PranetError as e:
        return f"not measurable with {options} ({e})"
    return f"{result.confidence:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--url", default=None, help="a running service (default: start one)")
    ap.add_argument("--repeats", type=int, default=5, help="timed requests per option set (after one warm-up)")
    ap.add_argument(
        "--scans",
        type=Path,
        default=None,
        help="also run every pair of this pairs.csv (default: $PRANET_DATA_DIR/scans/pairs.csv when it exists; "
        "'none' to skip)",
    )
    args = ap.parse_args()
    pairs_csv = args.scans if args.scans is not None else data_dir() / "scans" / "pairs.csv"
    with own_service() if args.url is None else nullcontext(args.url) as url:
        with PranetClient(url, timeout=300) as client:
            client.wait_ready(timeout=180)
            report(client, args.repeats, "1 onnxruntime thread" if args.url is None else url)
            if pairs_csv.is_file():
                scan_pairs(client, pairs_csv)
            elif args.scans is not None and str(args.scans) != "none":
                raise SystemExit(f"{args.scans}: no such file")


def report(client: PranetClient, repeats: int, where: str) -> None:
    source = read_point_cloud(EXAMPLE / "bun045.ply")
    target = read_point_cloud(EXAMPLE / "bun000.ply")
    T_true = np.loadtxt(EXAMPLE / "T_target_source.txt")
    model = client.model()
    rot0, trans0 = isotropic_errors(np.eye(4), T_true)
    print(f"model: {model['name']} {model['version']} (sha256 {model['sha256'][:12]})")
    print(
        f"pair: examples/bunny bun045 -> bun000 ({len(source)} / {len(target)} points), "
        f"true motion {rot0:.1f}° and {trans0 * 1e3:.0f} mm"
    )

    variants = {"default": {}, NO_RESCUE: {"rescue": False}}
    results: dict[str, RegistrationResult] = {}
    for name, options in list(variants.items()):  # warm-up: caches, pages, first-call allocations
        try:
            results[name], _ = timed(client, source, target, **options)
        except PranetError as e:
            if name == "default":
                raise
            print(f"{name}: not accepted by this service ({' '.join(str(e).split())[:120]})")
            del variants[name]
    latencies: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(repeats):
        for name, options in variants.items():
            results[name], ms = timed(client, source, target, **options)
            latencies[name].append(ms)

    default = results["default"]
    print(
        f"default request: {fmt_errors(default.transform, T_true)} off, "
        f"confidence {default.confidence:.2f} ({default.status}), won by the {default.candidate} candidate"
    )
    if default.trajectory:
        agent = fmt_errors(default.trajectory[-1].transform, T_true)
        print(f"the agent's own estimate (its last step, before ICP): {agent} off")
    median = {name: float(np.median(ms)) for name, ms in latencies.items()}
    side_by_side = ""
    if NO_RESCUE in results:
        plain = results[NO_RESCUE]
        errors = fmt_errors(plain.transform, T_true)
        print(f"{NO_RESCUE}: {errors} off, confidence {plain.confidence:.2f} ({plain.status})")
        side_by_side = f", {NO_RESCUE} {median[NO_RESCUE]:.0f} ms (ratio {median['default'] / median[NO_RESCUE]:.1f}x)"
    print(
        f"latency (median of {repeats}, interleaved, {where}): default {median['default']:.0f} ms{side_by_side}; "
        f"the default's stages: {stages(default)}"
    )
    centre = target.mean(axis=0)
    off = rotated_about_centroid(T_true, OFF_DEG, axis=1, centre=centre)
    print(
        f"confidence at the true pose: {confidence_of_pose(client, source, target, T_true)}; "
        f"{OFF_DEG:.0f}° off (about the vertical axis through the target's centroid): "
        f"{confidence_of_pose(client, source, target, off)}"
    )


def scan_pairs(client: PranetClient, pairs_csv: Path) -> None:
    """The default request on every pair of ``pairs_csv`` (the real-scan format): which candidates ran and won."""
    print(f"\nthe default request on {pairs_csv} (one request per pair):")
    print("| pair | points | error | confidence | won by | candidates tried | total ms |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    tried: dict[str, int] = {}
    won: dict[str, int] = {}
    registered = 0
    with open(pairs_csv, newline="") as f:
        rows = list(csv.DictReader(f))
    for row in rows:
        source = read_point_cloud(pairs_csv.parent / row["source"])
        target = read_point_cloud(pairs_csv.parent / row["target"])
        T_true = np.array(row["T_target_source"].split(), float).reshape(4, 4)
        sizes = f"{len(source)} / {len(target)}"
        try:
            result, ms = timed(client, source, target, return_trajectory=False)
        except PranetError as e:
            print(f"| {row['id']} | {sizes} | refused: {' '.join(str(e).split())[:100]} | | | | |")
            continue
        registered += 1
        for name in result.candidates:
            tried[name] = tried.get(name, 0) + 1
        won[str(result.candidate)] = won.get(str(result.candidate), 0) + 1
        candidates = ", ".join(f"{k} {v:.2f}" for k, v in result.candidates.items())
        print(
            f"| {row['id']} | {sizes} | {fmt_errors(result.transform, T_true)} | {result.confidence:.2f} "
            f"({result.status}) | {result.candidate} | {candidates} | {ms:.0f} |"
        )
    counts = "; ".join(f"{k}: tried on {n}, won on {won.get(k, 0)}" for k, n in tried.items())
    print(f"of {registered} registered pairs: {counts}")


def stages(result: RegistrationResult) -> str:
    return ", ".join(f"{k} {v:.0f} ms" for k, v in result.timing_ms.items() if k not in ("total", "queue") and v >= 0.5)


if __name__ == "__main__":
    main()
