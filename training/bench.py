"""``pranet-bench``: CPU latency, accuracy and throughput of PRANet against Open3D and small_gicp, side by side.

One run, the same unseen-category ModelNet40 pairs for every method (``make_pair(shape, setting,
pair_rng(seed, setting, i), 60, 0.5)``, as ``pranet-eval`` builds them), methods interleaved pair by pair
(their order rotated per pair) so that a noisy machine affects all of them alike. It reports:

1. per setting and method: median and p95 latency (ms), success rate (rotation < 1° and translation
   < 0.01, ``core.metrics``), median errors. Methods: ``pranet-v1`` (agent only, in-process),
   ``pranet-v2`` (agent + ICP: ``Engine.register`` with ``PAPER_V2``),
   ``pranet-v2-http`` (the same through a real ``pranet-serve`` on a loopback port, base64 clouds,
   client-side latency: encoding, HTTP, JSON), ``icp``, ``fgr-icp``, ``ransac-icp``
   (``training.baselines``), ``ransac-pranet-icp`` (the same RANSAC, refined by the engine's ICP
   instead of point-to-point ICP: the peer with the service's refinement) and ``small-gicp``
   (``small_gicp.align``, GICP from the identity);
2. each method's median latency as a ratio to RANSAC+ICP's and to FGR+ICP's;
3. where a registration's time goes (``Registration.timing_ms``; HTTP/JSON overhead = client latency
   minus the server's own total);
4. the reward net's achieved GFLOP/s (MatMul/Gemm/Conv FLOPs of one ``score.onnx`` call, counted from
   an onnxruntime profile, over the measured time per call and per agent step) against this CPU's
   sgemm throughput (numpy float32 matmul and one onnxruntime MatMul, measured in this run);
5. per-step latency of onnxruntime session options (optimisation level, threads, spinning, memory
   arena/pattern, execution mode) and of the int8 graphs, measured interleaved;
6. int8: reward drift against fp32 along the fp32 agent's trajectories (max/mean |Δ|, agreement of the
   chosen action), latency and accuracy; early stop: latency saving and accuracy cost;
7. service throughput (registrations/s) with 1 and 2 uvicorn workers under concurrent clients.

Examples::

    pranet-bench                                   # 200 pairs per setting, everything (~20 min)
    pranet-bench --pairs 20 --throughput-seconds 10 --markdown docs/bench.md
    pranet-bench --pairs 5 --methods pranet-v1,pranet-v2,icp --throughput-seconds 0 --ort-calls 0
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from pranet.core.metrics import SUCCESS_ROTATION_DEG, SUCCESS_TRANSLATION, isotropic_errors
from pranet.core.se3 import Array
from pranet.training.evaluate import nan_to_none
from pranet.training.samples import SETTINGS, Pair, make_pair, pair_rng

METHODS = (
    "pranet-v1",
    "pranet-v2",
    "pranet-v2-http",
    "pranet-adaptive",
    "pranet-adaptive-http",
    "icp",
    "fgr-icp",
    "ransac-icp",
    "ransac-pranet-icp",
    "small-gicp",
)
# (in-process, HTTP) method pairs whose time is broken down by stage
BREAKDOWN_PAIRS = (("pranet-v2", "pranet-v2-http"), ("pranet-adaptive", "pranet-adaptive-http"))
PRANET_IN_PROCESS = ("pranet-v1", "pranet-v2")
REFERENCES = ("ransac-icp", "fgr-icp")  # latency ratios are taken against these
DEFAULT_SETTINGS = ("noisy", "partial")
SMALL_GICP_DOWNSAMPLING = 0.01  # unit-sphere shapes: keeps (almost) every point
SERVER_START_TIMEOUT_S = 120.0


# --------------------------------------------------------------------------------------------------
# Small helpers.


def quantile(x: Sequence[float], q: float) -> float:
    a = np.asarray([v for v in x if v is not None and math.isfinite(v)], dtype=np.float64)
    return float(np.quantile(a, q)) if len(a) else math.nan


def median(x: Sequence[float]) -> float:
    return quantile(x, 0.5)


def fmt(x: float | None, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    if abs(x) >= 100:
        return f"{x:.0f}"
    return f"{x:.{digits}g}"


def md_table(head: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A markdown pipe table (readable as plain text too)."""
    cells = [[str(c) for c in head]] + [[c if isinstance(c, str) else fmt(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(head))]
    line = lambda r: "| " + " | ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) + " |"  # noqa: E731
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([line(cells[0]), sep, *(line(r) for r in cells[1:])])


def stats(samples: Sequence[float]) -> dict[str, float]:
    return {"median": median(samples), "p95": quantile(samples, 0.95), "n": len(samples)}


# --------------------------------------------------------------------------------------------------
# Methods: each maps (pair, pair seed) to (T_target_source, latency ms, extra).


@dataclass
class Outcome:
    transform: Array
    ms: float
    extra: dict[str, Any] = field(default_factory=dict)


MethodFn = Callable[[Pair, int], Outcome]


def small_gicp_align(
    source: Array, target: Array, max_distance: float = 0.5, threads: int = 1, max_iterations: int = 100
) -> Array:
    """GICP from the identity with small_gicp (covariances from 20 neighbours after a fine voxel grid)."""
    import small_gicp

    r = small_gicp.align(
        np.ascontiguousarray(target, dtype=np.float64),
        np.ascontiguousarray(source, dtype=np.float64),
        registration_type="GICP",
        downsampling_resolution=SMALL_GICP_DOWNSAMPLING,
        max_correspondence_distance=max_distance,
        num_threads=threads,
        max_iterations=max_iterations,
    )
    return np.asarray(r.T_target_source, dtype=np.float64).copy()


def pranet_method(engine: Any, config: Any) -> MethodFn:
    """PRANet in-process through ``engine`` (``pranet.engine.Engine``) as ``config`` (a ``RegistrationConfig``)."""

    def run(pair: Pair, seed: int) -> Outcome:
        t0 = time.perf_counter()
        reg = engine.register(pair.source, pair.target, config, np.random.default_rng(seed))
        ms = (time.perf_counter() - t0) * 1e3
        extra = {
            "timing_ms": reg.timing_ms,
            "n_steps": len(reg.trajectory),
            "agent_transform": reg.agent_T_target_source,
        }
        if reg.agent is not None:  # steps after a translation: re-scored by head.onnx when the runtime reuses
            moved = set(np.asarray(engine.scorer.table.translation_indices).tolist())
            extra["after_translation"] = sum(a.action in moved for a in reg.agent.steps[:-1])
        return Outcome(reg.T_target_source, ms, extra)

    return run


def refined_by(coarse: Callable[[Array, Array, np.random.Generator], Array], icp: Any):
    """``coarse`` (a baseline without refinement) followed by PRANet's ICP (an ``IcpFn``, unit frame), as the
    pipeline runs it: the classical peer with the same refinement as the service."""
    from pranet.core.preprocess import fit_normalization

    def fn(source: Array, target: Array, rng: np.random.Generator) -> Array:
        T = coarse(source, target, rng)
        norm = fit_normalization(source, target)
        refined = icp(norm.to_unit(source), norm.to_unit(target), norm.transform_to_unit(T))
        return norm.transform_to_world(refined.transform)

    return fn


def baseline_method(fn: Callable[[Array, Array, np.random.Generator], Array]) -> MethodFn:
    def run(pair: Pair, seed: int) -> Outcome:
        rng = np.random.default_rng(seed)
        t0 = time.perf_counter()
        T = fn(pair.source, pair.target, rng)
        return Outcome(np.asarray(T, dtype=np.float64), (time.perf_counter() - t0) * 1e3)

    return run


def request_body(
    pair: Pair, seed: int, icp: bool = True, steps: Sequence[int] | None = None, adaptive: bool = False
) -> bytes:
    """``adaptive``: the service's default exit checks and rescue; else every step, no rescue (the paper's v2)."""
    from pranet.core.registration_config import SERVICE_DEFAULT
    from pranet.core.wire import encode_cloud

    body: dict[str, Any] = {
        "source": encode_cloud(pair.source),
        "target": encode_cloud(pair.target),
        "icp": icp,
        "seed": seed,
        "return_trajectory": False,
        "exit_checks": list(SERVICE_DEFAULT.exit_checks) if adaptive else [],
        "rescue": adaptive,
    }
    if steps is not None:
        body["steps"] = list(steps)
    return json.dumps(body).encode()


def http_method(client: Any, steps: Sequence[int] | None = None, adaptive: bool = False) -> MethodFn:
    """``pranet-v2`` (or the adaptive variant) over HTTP; the latency is the client's: encoding, request, parsing."""

    def run(pair: Pair, seed: int) -> Outcome:
        t0 = time.perf_counter()
        body = request_body(pair, seed, steps=steps, adaptive=adaptive)
        r = client.post("/register", content=body, headers={"Content-Type": "application/json"})
        if r.status_code != 200:
            raise RuntimeError(f"HTTP {r.status_code}: {r.text[:300]}")
        data = r.json()
        ms = (time.perf_counter() - t0) * 1e3
        extra = {"server_timing_ms": data["timing_ms"], "exit_checks": data.get("exit_checks", [])}
        return Outcome(np.asarray(data["transform"], dtype=np.float64), ms, extra)

    return run


# --------------------------------------------------------------------------------------------------
# A real pranet-serve on a loopback port.


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def served(settings: dict[str, str], log_dir: Path):
    """``pranet-serve`` (``python -m pranet.service.cli``) with ``PRANET_*`` ``settings``; yields its URL once
    every worker answers /ready; SIGTERM on exit."""
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
        yield url
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


# --------------------------------------------------------------------------------------------------
# FLOPs of an ONNX graph (from an onnxruntime profile: concrete shapes of every node) and sgemm.


def _shape(entry: dict[str, Any]) -> list[int]:
    return list(next(iter(entry.values())))


def node_flops(op: str, inputs: list[list[int]], outputs: list[list[int]]) -> float:
    """Multiply-adds x 2 of MatMul/Gemm/Conv (and their int8 forms) from concrete shapes; 0 for other ops."""
    if not outputs or not inputs:
        return 0.0
    out = outputs[0]
    if op in ("MatMul", "MatMulInteger", "DynamicQuantizeMatMul", "FusedMatMul", "MatMulIntegerToFloat"):
        a = inputs[0]
        return 2.0 * float(np.prod(out)) * (a[-1] if a else 1)
    if op == "Gemm":
        m = out[0] if out else 1
        return 2.0 * float(np.prod(out)) * (float(np.prod(inputs[0])) / max(m, 1))
    if op in ("Conv", "ConvInteger", "FusedConv"):
        w = inputs[1]
        return 2.0 * float(np.prod(out)) * float(np.prod(w[1:]))
    return 0.0


def target_only_nodes(model_path: Path) -> set[str]:
    """Names of the score graph's nodes that depend on the target inputs and initializers only:
    work recomputed at every agent step although the target never changes within a registration."""
    import onnx

    g = onnx.load(str(model_path), load_external_data=False).graph
    constant = {i.name for i in g.initializer}
    target = {i.name for i in g.input if i.name.startswith("target")}
    source = {i.name for i in g.input} - target
    depends: dict[str, tuple[bool, bool]] = {n: (False, True) for n in target}  # (on source, on target)
    depends.update({n: (True, False) for n in source})
    names: set[str] = set()
    for node in g.node:  # topologically ordered
        ins = [depends.get(i, (False, False)) for i in node.input if i and i not in constant]
        on_source = any(s for s, _ in ins)
        on_target = any(t for _, t in ins)
        for o in node.output:
            depends[o] = (on_source, on_target)
        if on_target and not on_source:
            names.add(node.name)
    return names


def graph_flops(model_path: Path, feeds: dict[str, np.ndarray]) -> dict[str, Any]:
    """FLOPs of one call of ``model_path`` on ``feeds`` (unoptimised graph, so the nodes are the exported ones)."""
    import onnxruntime as ort

    with tempfile.TemporaryDirectory() as tmp:
        opts = ort.SessionOptions()
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
        opts.intra_op_num_threads = 1
        opts.enable_profiling = True
        opts.profile_file_prefix = str(Path(tmp) / "profile")
        sess = ort.InferenceSession(str(model_path), sess_options=opts, providers=["CPUExecutionProvider"])
        sess.run(None, {i.name: feeds[i.name] for i in sess.get_inputs()})
        events = json.loads(Path(sess.end_profiling()).read_text())
    target_only = target_only_nodes(model_path)
    total, on_target, by_op = 0.0, 0.0, {}
    for e in events:
        if e.get("cat") != "Node" or not str(e.get("name", "")).endswith("_kernel_time"):
            continue
        args = e.get("args", {})
        op = args.get("op_name", "")
        flops = node_flops(
            op,
            [_shape(x) for x in args.get("input_type_shape", [])],
            [_shape(x) for x in args.get("output_type_shape", [])],
        )
        total += flops
        by_op[op] = by_op.get(op, 0.0) + flops
        if e["name"][: -len("_kernel_time")] in target_only:
            on_target += flops
    return {"flops": total, "target_only_flops": on_target, "by_op": {k: v for k, v in by_op.items() if v}}


SGEMM_CODE = """
import os, sys, time, numpy as np
n, reps = int(sys.argv[1]), int(sys.argv[2])
rng = np.random.default_rng(0)
a = rng.random((n, n), dtype=np.float32); b = rng.random((n, n), dtype=np.float32); c = a @ b
ts = []
for _ in range(reps):
    t0 = time.perf_counter(); np.matmul(a, b, out=c); ts.append(time.perf_counter() - t0)
print(2.0 * n ** 3 / float(np.median(ts)) / 1e9)
"""


def numpy_sgemm_gflops(n: int, threads: int, reps: int = 20) -> float:
    """numpy float32 ``n x n`` matmul GFLOP/s with ``threads`` BLAS threads (a fresh process: the BLAS
    reads its thread count at import)."""
    env = {**os.environ, **{k: str(threads) for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}}
    out = subprocess.run(
        [sys.executable, "-c", SGEMM_CODE, str(n), str(reps)], env=env, capture_output=True, text=True, check=True
    )
    return float(out.stdout.strip())


def ort_sgemm_gflops(n: int, threads: int, reps: int = 20) -> float:
    """GFLOP/s of one onnxruntime MatMul ``n x n`` (the kernels the reward net runs on)."""
    import onnxruntime as ort
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        [helper.make_node("MatMul", ["a", "b"], ["c"])],
        "sgemm",
        [helper.make_tensor_value_info(x, TensorProto.FLOAT, [n, n]) for x in ("a", "b")],
        [helper.make_tensor_value_info("c", TensorProto.FLOAT, [n, n])],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = min(model.ir_version, 9)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    sess = ort.InferenceSession(
        model.SerializeToString(),
        sess_options=opts,
        providers=["CPUExecutionProvider"],
    )
    rng = np.random.default_rng(0)
    feeds = {x: rng.random((n, n), dtype=np.float32) for x in ("a", "b")}
    sess.run(None, feeds)
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        sess.run(None, feeds)
        ts.append(time.perf_counter() - t0)
    return 2.0 * n**3 / float(np.median(ts)) / 1e9


# --------------------------------------------------------------------------------------------------
# onnxruntime options, measured interleaved.

ORT_VARIANTS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("default (all, 2 threads, sequential, arena, mem pattern, no spinning)", {}),
    ("optimization=none", {"optimization": "none"}),
    ("optimization=basic", {"optimization": "basic"}),
    ("optimization=extended", {"optimization": "extended"}),
    ("threads=1", {"threads": 1}),
    ("spinning on (onnxruntime's default)", {"spinning": True}),
    ("memory arena off", {"arena": False}),
    ("memory pattern off", {"mem_pattern": False}),
    ("execution=parallel (2 inter-op threads)", {"execution": "parallel"}),
    ("int8", {"precision": "int8"}),
    ("int8, threads=1", {"precision": "int8", "threads": 1}),
)


def ort_variants_table(
    model_dir: str | None,
    int8_dir: Path | None,
    threads: int,
    source: Array,
    target: Array,
    calls: int,
    per_round: int = 10,
) -> list[dict[str, Any]]:
    """ms per score call (= per agent step, minus the agent's own bookkeeping) and per target embedding, for
    each variant, ``calls`` calls in all: in rounds of ``per_round`` calls per variant, the variants' order
    rotated per round. Only one variant's sessions exist at a time (opened for its turn, then closed), as in a
    service worker: idle thread pools of other sessions, spinning, would otherwise slow whichever runs next."""
    import gc

    from pranet.engine.runtime import RewardModel

    variants = []
    for label, kw in ORT_VARIANTS:
        kw = {"threads": threads, **kw}
        if kw.get("precision") == "int8":
            if int8_dir is None:
                continue
            variants.append((label, kw, int8_dir))
        else:
            variants.append((label, kw, model_dir))
    samples: dict[str, list[float]] = {label: [] for label, _, _ in variants}
    round_best: dict[str, list[float]] = {label: [] for label, _, _ in variants}
    round_median: dict[str, list[float]] = {label: [] for label, _, _ in variants}
    embed: dict[str, list[float]] = {label: [] for label, _, _ in variants}
    graph_calls: dict[str, dict[str, int]] = {label: {"full": 0, "head": 0} for label, _, _ in variants}
    per_round = max(1, min(per_round, calls))
    rounds = max(1, calls // per_round)
    for r in range(rounds):
        k = r % len(variants)
        for label, kw, where in variants[k:] + variants[:k]:  # rotated: no variant always runs first
            # The same source every call: with head reuse the runtime would re-score it with head.onnx alone
            # (it has not moved), and this table would time the MLP heads instead of score.onnx.
            model = RewardModel.load(where, reuse_translations=False, **kw)
            f = model.score_fn(target)
            f(source, target)  # first call: kNN graph, allocations
            this_round = []
            for _ in range(per_round):
                t0 = time.perf_counter()
                f(source, target)
                this_round.append((time.perf_counter() - t0) * 1e3)
            for graph, n in f.calls.items():
                graph_calls[label][graph] += n
            samples[label] += this_round
            round_best[label].append(min(this_round))
            round_median[label].append(float(np.median(this_round)))
            t0 = time.perf_counter()
            model.embed(target)
            embed[label].append((time.perf_counter() - t0) * 1e3)
            del f, model
            gc.collect()  # close the sessions (and their thread pools) before the next variant
    default = variants[0][0]
    return [
        {
            "variant": label,
            "options": kw,
            "score_ms": median(samples[label]),
            "score_min_ms": min(samples[label]),
            "score_p90_ms": quantile(samples[label], 0.9),
            "embed_ms": median(embed[label]),
            # Paired: per round, this variant's best (median) call over the default's in the same round.
            "vs_default": median([a / b for a, b in zip(round_best[label], round_best[default], strict=True)]),
            "vs_default_busy": median([a / b for a, b in zip(round_median[label], round_median[default], strict=True)]),
            "calls": len(samples[label]),
            "graph_calls": graph_calls[label],  # score.onnx ("full") and head.onnx runs: head must stay 0
        }
        for label, kw, _ in variants
    ]


# --------------------------------------------------------------------------------------------------
# int8 drift: both precisions scored on the fp32 agent's states.


class DriftScorer:
    """A scorer running the fp32 model (whose rewards drive the agent) and the int8 one on the same states."""

    def __init__(self, fp32: Any, int8: Any):
        self.fp32, self.int8 = fp32, int8
        self.table, self.schedule, self.n_points = fp32.table, fp32.schedule, fp32.n_points
        self.pairs: list[tuple[np.ndarray, np.ndarray]] = []

    def score_fn(self, target: Any) -> Callable[[Array, Array], np.ndarray]:
        f32, f8 = self.fp32.score_fn(target), self.int8.score_fn(target)

        def score(source: Array, tgt: Array) -> np.ndarray:
            r32 = np.asarray(f32(source, tgt), dtype=np.float64)
            self.pairs.append((r32, np.asarray(f8(source, tgt), dtype=np.float64)))
            return r32

        return score


def drift_summary(pairs: Sequence[tuple[np.ndarray, np.ndarray]], table: Any, schedule: Sequence[int]) -> dict:
    """Per step: |Δ| over all actions, and whether both precisions pick the same action of the step's scale."""
    if not pairs:
        return {}
    diffs = np.array([np.abs(a - b) for a, b in pairs])
    bounds = np.cumsum(schedule)
    n_per_reg = int(bounds[-1])
    agree = []
    for j, (a, b) in enumerate(pairs):
        scale = int(np.searchsorted(bounds, j % n_per_reg, side="right"))
        idx = table.indices_of_scale(min(scale, len(schedule) - 1))
        agree.append(np.argmax(a[idx]) == np.argmax(b[idx]))
    scale_of_rewards = float(np.mean([np.abs(a).mean() for a, _ in pairs]))
    return {
        "states": len(pairs),
        "max_abs": float(diffs.max()),
        "mean_abs": float(diffs.mean()),
        "p99_abs": float(np.quantile(diffs, 0.99)),
        "mean_abs_reward_fp32": scale_of_rewards,
        "argmax_agreement": float(np.mean(agree)),
    }


# --------------------------------------------------------------------------------------------------
# The run.


@dataclass
class Record:
    setting: str
    pair: int
    method: str
    ms: float
    rotation_deg: float
    translation: float
    success: bool
    error: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    transform: list[list[float]] | None = None  # the estimate T_target_source


def score_pair(method: str, setting: str, i: int, pair: Pair, out: Outcome | None, error: str | None) -> Record:
    if out is None:
        return Record(setting, i, method, math.nan, math.nan, math.nan, False, error)
    rot, trans = isotropic_errors(out.transform, pair.T_gt)
    ok = bool(rot < SUCCESS_ROTATION_DEG and trans < SUCCESS_TRANSLATION)
    return Record(setting, i, method, out.ms, float(rot), float(trans), ok, None, out.extra, out.transform.tolist())


def summarize(records: Sequence[Record]) -> dict[str, Any]:
    ok = [r for r in records if r.error is None]
    return {
        "n": len(records),
        "errors": len(records) - len(ok),
        "ms_median": median([r.ms for r in ok]),
        "ms_p95": quantile([r.ms for r in ok], 0.95),
        "success": float(np.mean([r.success for r in records])) if records else math.nan,
        "rot_median": median([r.rotation_deg for r in ok]),
        "trans_median": median([r.translation for r in ok]),
        "steps_mean": float(np.mean(steps))
        if (steps := [r.extra["n_steps"] for r in ok if "n_steps" in r.extra])
        else math.nan,
    }


def as_float32(pair: Pair) -> Pair:
    """The pair with both clouds rounded to float32, as the HTTP client sends them: every method, in-process or
    over HTTP, then registers exactly the same numbers."""
    return replace(
        pair,
        source=pair.source.astype(np.float32).astype(np.float64),
        target=pair.target.astype(np.float32).astype(np.float64),
    )


def pair_seed(seed: int, setting: str, i: int) -> int:
    """One integer seed per pair, shared by every method (the service takes it as ``seed``): PRANet in-process
    and over HTTP resample the same points."""
    return int(np.random.default_rng([seed, SETTINGS.index(setting), i, 99]).integers(0, 2**31 - 1))


def environment(threads: int) -> dict[str, Any]:
    from importlib.metadata import PackageNotFoundError, version

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    env: dict[str, Any] = {
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "threads": threads,
        "load_avg_1m": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "nice": os.nice(0) if hasattr(os, "nice") else None,
        "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"),
        "python": platform.python_version(),
    }
    for dist in ("numpy", "onnxruntime", "open3d-cpu", "open3d", "small_gicp", "httpx", "uvicorn"):
        try:
            env[dist] = version(dist)
        except PackageNotFoundError:
            pass
    return env


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="pranet-bench",
        description=__doc__.split("\n\n")[0] if __doc__ else None,
        epilog="See docs/PERFORMANCE.md for the method and the measured tables.",
    )
    p.add_argument("--pairs", type=int, default=200, help="pairs per setting (default 200)")
    p.add_argument("--settings", default=",".join(DEFAULT_SETTINGS), help="comma-separated (default noisy,partial)")
    p.add_argument("--methods", default=",".join(METHODS), help=f"subset of {','.join(METHODS)} (default: all)")
    p.add_argument("--model", default=None, help="model directory (default: the shipped model)")
    p.add_argument("--data-dir", default=None, help="data root (default: $PRANET_DATA_DIR, else ../shared/data)")
    p.add_argument("--seed", type=int, default=1234)
    p.add_argument("--steps", default=None, help="agent steps per scale, e.g. 20,40 (default: the model's schedule)")
    p.add_argument("--threads", type=int, default=2, help="onnxruntime/Open3D/small_gicp threads (default 2)")
    p.add_argument("--no-early-stop", dest="early_stop", action="store_false", help="skip the early-stop table")
    p.add_argument("--no-int8", dest="int8", action="store_false", help="skip the int8 drift/accuracy table")
    p.add_argument("--ort-calls", type=int, default=200, help="score calls per onnxruntime variant (0: skip)")
    p.add_argument("--throughput-seconds", type=float, default=10.0, help="per worker count (0: skip)")
    p.add_argument("--clients", type=int, default=4, help="concurrent client threads for throughput (default 4)")
    p.add_argument("--workers", default="1,2", help="uvicorn worker counts for throughput (default 1,2)")
    p.add_argument("--markdown", type=Path, default=None, help="also write the tables (with the command) here")
    p.add_argument("--json", type=Path, default=None, help="write summaries and per-pair records here")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    args = p.parse_args(argv)
    unknown = {x.strip() for x in args.methods.split(",") if x.strip()} - set(METHODS)
    settings = [s.strip() for s in args.settings.split(",") if s.strip()]
    args.methods = [m for m in METHODS if m in {x.strip() for x in args.methods.split(",")}]
    if not args.methods or any(s not in SETTINGS for s in settings) or unknown:
        p.error(f"--methods from {','.join(METHODS)}; --settings from {','.join(SETTINGS)}")
    args.settings = settings
    args.workers = [int(w) for w in args.workers.split(",") if w.strip()]
    args.steps = [int(x) for x in args.steps.split(",")] if args.steps else None
    if args.pairs < 1:
        p.error("--pairs must be at least 1")
    return args


def log(args: argparse.Namespace, msg: str) -> None:
    if not args.quiet:
        print(f"pranet-bench: {msg}", file=sys.stderr, flush=True)


def run(args: argparse.Namespace, command: str) -> dict[str, Any]:  # noqa: C901 (one linear script)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))  # Open3D reads it at import
    # OpenMP threads (Open3D, small_gicp) that busy-wait at barriers collapse when a core is taken by another
    # process: small_gicp with 2 threads measured 800 ms instead of 4 ms per pair beside a training run.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from pranet.core.registration_config import PAPER_V1, PAPER_V2, SERVICE_DEFAULT
    from pranet.engine.engine import Engine
    from pranet.engine.runtime import RewardModel, default_model_dir, read_card
    from pranet.training import baselines
    from pranet.training.data import data_dir, load_modelnet40, test_indices

    t_start = time.perf_counter()
    result: dict[str, Any] = {"command": command, "environment": environment(args.threads)}
    result["config"] = {k: v for k, v in vars(args).items() if k not in ("markdown", "json", "quiet")}
    data = load_modelnet40(data_dir(args.data_dir), "test")
    idx = test_indices(data.labels)[: args.pairs]
    pairs = {
        s: [as_float32(make_pair(data.points[j], s, pair_rng(args.seed, s, i), 60.0, 0.5)) for i, j in enumerate(idx)]
        for s in args.settings
    }
    model_dir = Path(args.model) if args.model else default_model_dir()
    engine = Engine.load(model_dir, threads=args.threads)
    scorer = engine.scorer
    result["model"] = {**scorer.info(), "dir": str(args.model or "default (shipped)")}
    result["model_schedule"] = list(scorer.schedule)
    steps = {"schedule": tuple(args.steps) if args.steps else None}
    v1, v2 = PAPER_V1.with_(**steps), PAPER_V2.with_(**steps)
    icp = engine.icp(v2.icp_stages)
    tmp = Path(tempfile.mkdtemp(prefix="pranet-bench-"))
    try:
        # int8 graphs: the model directory's own, else quantized now into a temporary copy.
        int8_dir: Path | None = None
        int8_note = ""
        if args.int8 or args.ort_calls > 0:
            try:
                read_card(model_dir, precision="int8")
                int8_dir, int8_note = model_dir, "the model directory's int8 graphs"
            except Exception:
                from pranet.model.quantize import quantize_model_dir

                int8_dir = tmp / "model-int8"
                shutil.copytree(model_dir, int8_dir)
                quantize_model_dir(int8_dir)
                int8_note = "quantized in this run (pranet-export --int8) into a temporary copy"
        result["int8_source"] = int8_note

        fns: dict[str, MethodFn] = {
            "pranet-v1": pranet_method(engine, v1),
            "pranet-v2": pranet_method(engine, v2),
            "pranet-adaptive": pranet_method(engine, SERVICE_DEFAULT.with_(**steps)),
            "icp": baseline_method(baselines.icp),
            "fgr-icp": baseline_method(baselines.fgr_icp),
            "ransac-icp": baseline_method(baselines.ransac_icp),
            "ransac-pranet-icp": baseline_method(refined_by(baselines.ransac, icp)),
            "small-gicp": baseline_method(
                lambda s, t, rng: small_gicp_align(s, t, baselines.ICP_MAX_DISTANCE, args.threads)
            ),
        }
        extra_fns: dict[str, MethodFn] = {}
        # Every step through score.onnx (no head-only re-scoring of translated sources): what that reuse buys.
        scorer_full = RewardModel.load(model_dir, threads=args.threads, reuse_translations=False)
        extra_fns["pranet-full"] = pranet_method(Engine(scorer_full), v2)
        if args.early_stop:
            extra_fns["pranet-es"] = pranet_method(engine, v2.with_(early_stop=True))
        drift: DriftScorer | None = None
        if args.int8 and int8_dir is not None:
            scorer8 = RewardModel.load(int8_dir, threads=args.threads, precision="int8")
            extra_fns["pranet-int8"] = pranet_method(Engine(scorer8), v2)
            drift = DriftScorer(scorer, scorer8)
            extra_fns["drift"] = pranet_method(Engine(drift), v1)
        records: list[Record] = []
        with served(server_settings(args.model, args.threads, 1, "fp32"), tmp) as url:
            import httpx

            client = httpx.Client(base_url=url, timeout=120.0)
            if "pranet-v2-http" in args.methods:
                fns["pranet-v2-http"] = http_method(client, args.steps)
            if "pranet-adaptive-http" in args.methods:
                fns["pranet-adaptive-http"] = http_method(client, args.steps, adaptive=True)
            order = [m for m in args.methods if m in fns] + list(extra_fns)
            allfns = {**fns, **extra_fns}
            warm = pairs[args.settings[0]][0]
            for m in order:  # first calls: imports, allocations, connections
                allfns[m](warm, 0)
            if drift is not None:
                drift.pairs.clear()
            total = len(args.settings) * args.pairs
            done = 0
            for s in args.settings:
                for i, pair in enumerate(pairs[s]):
                    seed = pair_seed(args.seed, s, i)
                    k = i % len(order)
                    for m in order[k:] + order[:k]:
                        try:
                            out, err = allfns[m](pair, seed), None
                        except Exception as e:  # counted as a failure, reported
                            out, err = None, f"{type(e).__name__}: {e}"
                        records.append(score_pair(m, s, i, pair, out, err))
                    done += 1
                    if done % max(1, total // 20) == 0 or done == total:
                        log(args, f"pairs {done}/{total} ({time.perf_counter() - t_start:.0f} s)")
            client.close()
        result["summary"] = {
            s: {m: summarize([r for r in records if r.setting == s and r.method == m]) for m in order if m in fns}
            for s in args.settings
        }

        # Early stop, int8 and no-reuse ran agent + ICP once per pair: v2 is that run, v1 its agent result
        # (minus ICP time).
        tags = {"pranet-es": "early stop", "pranet-int8": "int8", "pranet-full": "no head reuse"}
        derived: list[Record] = []
        for r in records:
            if r.method not in tags:
                continue
            tag = tags[r.method]
            pair = pairs[r.setting][r.pair]
            if r.error is not None:
                derived += [replace(r, method=f"pranet-v1 {tag}"), replace(r, method=f"pranet-v2 {tag}")]
                continue
            v1 = Outcome(r.extra["agent_transform"], r.ms - r.extra["timing_ms"].get("icp", 0.0), r.extra)
            derived += [score_pair(f"pranet-v1 {tag}", r.setting, r.pair, pair, v1, None)]
            derived += [replace(r, method=f"pranet-v2 {tag}")]
        variants = [f"pranet-{v} {tag}" for tag in tags.values() for v in ("v1", "v2")]
        result["variants"] = {
            s: {m: summarize([r for r in derived if r.setting == s and r.method == m]) for m in variants}
            for s in args.settings
        }
        records += derived

        if drift is not None:
            result["int8_drift"] = drift_summary(drift.pairs, scorer.table, args.steps or scorer.schedule)

        # Per-step costs, FLOPs, sgemm.
        src_u, tgt_u = unit_clouds(pairs[args.settings[0]][0], scorer.n_points, args.seed)
        result["flops"] = flops_table(model_dir, scorer_full, src_u, tgt_u, records)
        result["sgemm"] = sgemm_table(args.threads)
        if args.ort_calls > 0:
            log(args, "onnxruntime options")
            result["ort_variants"] = ort_variants_table(
                args.model, int8_dir, args.threads, src_u, tgt_u, args.ort_calls
            )
        if args.throughput_seconds > 0:
            result["throughput"] = []
            bodies = [  # the service's default request: exit checks and rescue
                request_body(p, pair_seed(args.seed, args.settings[0], i), steps=args.steps, adaptive=True)
                for i, p in enumerate(pairs[args.settings[0]][:8])
            ]
            for w in args.workers:
                t_per = max(1, args.threads // w)
                log(args, f"throughput: {w} worker(s) x {t_per} thread(s), {args.clients} clients")
                with served(server_settings(args.model, t_per, w, "fp32"), tmp) as url:
                    tp = throughput(url, bodies, args.clients, args.throughput_seconds)
                result["throughput"].append({"workers": w, "threads_per_worker": t_per, **tp})
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    result["records"] = records
    result["wall_s"] = time.perf_counter() - t_start
    return result


def unit_clouds(pair: Pair, n_points: int, seed: int) -> tuple[Array, Array]:
    """The pair as ``register`` hands it to the model: normalised to the unit frame, resampled to N points."""
    from pranet.core.preprocess import check_cloud, fit_normalization, resample

    src, tgt = check_cloud(pair.source, "source"), check_cloud(pair.target, "target")
    norm = fit_normalization(src, tgt)
    rng = np.random.default_rng(seed)
    return resample(norm.to_unit(src), n_points, rng), resample(norm.to_unit(tgt), n_points, rng)


def flops_table(model_dir: Path, scorer: Any, source: Array, target: Array, records: Sequence[Record]) -> dict:
    """FLOPs per call of the graphs, the measured time per call and per agent step, the achieved GFLOP/s.

    ``scorer`` must not reuse pair features (``reuse_translations=False``): the timed calls repeat one pose.
    An agent step's FLOPs average score.onnx and head.onnx calls by the share of steps after a translation
    in the pranet-v1 records (what the default runtime re-scores with the head alone).
    """
    from pranet.core.knn import knn_indices
    from pranet.engine.runtime import HEAD_GRAPH, graph_files

    embed_file, score_file = graph_files("fp32")
    pts = np.asarray(source, dtype=np.float32)[None]
    tpts = np.asarray(target, dtype=np.float32)[None]
    feats, cen, tknn = scorer.embed(tpts)
    score_feeds = {
        "points": pts,
        "knn": knn_indices(pts, scorer.k),
        "target_points": tpts,
        "target_features": feats,
        "target_centroid": cen,
    }
    fl_score = graph_flops(model_dir / score_file, score_feeds)
    fl_embed = graph_flops(model_dir / embed_file, {"points": tpts, "knn": tknn})
    f = scorer.score_fn(target)
    f(source, target)
    score_ms, embed_ms, head_ms = [], [], []
    for _ in range(50):
        t0 = time.perf_counter()
        f(source, target)
        score_ms.append((time.perf_counter() - t0) * 1e3)
    for _ in range(10):
        t0 = time.perf_counter()
        scorer.embed(tpts)
        embed_ms.append((time.perf_counter() - t0) * 1e3)
    head_flops = math.nan
    if (model_dir / HEAD_GRAPH).is_file():
        import onnxruntime as ort

        full = ort.InferenceSession(str(model_dir / score_file), providers=["CPUExecutionProvider"])
        pair = full.run(["pair_features"], {i.name: score_feeds[i.name] for i in full.get_inputs()})[0]
        head_feeds = {"pair_features": pair, "offset": np.zeros((1, 3), np.float32)}
        head_flops = graph_flops(model_dir / HEAD_GRAPH, head_feeds)["flops"]
        head = ort.InferenceSession(str(model_dir / HEAD_GRAPH), providers=["CPUExecutionProvider"])
        for _ in range(50):
            t0 = time.perf_counter()
            head.run(None, head_feeds)
            head_ms.append((time.perf_counter() - t0) * 1e3)
    v1 = [r for r in records if r.method == "pranet-v1" and r.error is None and r.extra.get("n_steps")]
    step_ms = median([r.extra["timing_ms"]["agent_steps"] / r.extra["n_steps"] for r in v1])
    share = sum(r.extra.get("after_translation", 0) for r in v1) / max(1, sum(r.extra["n_steps"] for r in v1))
    step_flops = fl_score["flops"] if math.isnan(head_flops) else (1 - share) * fl_score["flops"] + share * head_flops
    return {
        "score_flops": fl_score["flops"],
        "score_target_only_flops": fl_score["target_only_flops"],
        "score_by_op": fl_score["by_op"],
        "embed_flops": fl_embed["flops"],
        "head_flops": head_flops,
        "score_ms": median(score_ms),
        "embed_ms": median(embed_ms),
        "head_ms": median(head_ms) if head_ms else math.nan,
        "agent_step_ms": step_ms,
        "agent_step_flops": step_flops,
        "head_step_share": share,
    }


def sgemm_table(threads: int) -> list[dict[str, Any]]:
    rows = []
    for t in sorted({1, threads}):
        for n in (512, 1024):
            rows.append({"impl": "numpy float32 matmul", "n": n, "threads": t, "gflops": numpy_sgemm_gflops(n, t)})
        try:
            rows.append({"impl": "onnxruntime MatMul", "n": 1024, "threads": t, "gflops": ort_sgemm_gflops(1024, t)})
        except ImportError:  # onnx (train extra) missing
            pass
    return rows


# --------------------------------------------------------------------------------------------------
# Report.

LABELS = {
    "pranet-v1": "PRANet-v1 (agent, in-process)",
    "pranet-v2": "PRANet-v2 (agent + ICP, in-process)",
    "pranet-v2-http": "PRANet-v2 over HTTP (client side)",
    "pranet-adaptive": "PRANet adaptive (v2 + exit checks 20/40 + rescue, in-process)",
    "pranet-adaptive-http": "PRANet adaptive over HTTP (client side; the service's default)",
    "icp": "Open3D ICP (from identity)",
    "fgr-icp": "FGR + ICP",
    "ransac-icp": "RANSAC + ICP",
    "ransac-pranet-icp": "RANSAC + PRANet's ICP (the service's refinement)",
    "small-gicp": "small_gicp GICP (from identity)",
}


def report(result: dict[str, Any]) -> str:  # noqa: C901 (sections, one after the other)
    out: list[str] = []
    env, model = result["environment"], result["model"]
    out.append(
        f"Model: {model['name']} {model['version']} (sha256 {model['sha256'][:12]}, {model['dir']}). "
        f"CPU: {env['cpu']}, {env['cpu_count']} cores, {env['threads']} threads per method; load average at start "
        f"{fmt(env.get('load_avg_1m'))}, nice {env.get('nice')}, OMP_WAIT_POLICY={env.get('OMP_WAIT_POLICY')}. "
        f"onnxruntime {env.get('onnxruntime')}, "
        f"open3d {env.get('open3d-cpu') or env.get('open3d')}, small_gicp {env.get('small_gicp')}. "
        f"Wall time {result['wall_s']:.0f} s."
    )
    cfg = result.get("config", {})
    out.append(
        f"\nPairs: {cfg.get('pairs')} per setting (unseen ModelNet40 categories, seed {cfg.get('seed')}, rotation "
        f"≤ 60°, translation ≤ 0.5); agent steps per scale: {cfg.get('steps') or list(result['model_schedule'])}."
    )
    settings = list(result["summary"])
    out.append("\n## Latency and success\n")
    out.append(
        f"Per setting and method: median and p95 latency over the pairs, success = rotation < {SUCCESS_ROTATION_DEG}° "
        f"and translation < {SUCCESS_TRANSLATION}; median isotropic errors."
    )
    rows = []
    for s in settings:
        for m, v in result["summary"][s].items():
            rows.append(
                [
                    s,
                    LABELS.get(m, m),
                    str(v["n"]),
                    v["ms_median"],
                    v["ms_p95"],
                    f"{100 * v['success']:.1f}",
                    v["rot_median"],
                    v["trans_median"],
                    str(v["errors"]),
                ]
            )
    out.append(
        md_table(
            ["setting", "method", "pairs", "median ms", "p95 ms", "success %", "rot° med", "trans med", "errors"], rows
        )
    )

    refs = [r for r in REFERENCES if all(r in result["summary"][s] for s in settings)]
    if refs:
        out.append("\n## Median latency relative to RANSAC+ICP and FGR+ICP (same run)\n")
        head = ["method"] + [f"÷ {LABELS[r].split(' ')[0]}+ICP ({s})" for s in settings for r in refs]
        rows = []
        for m in result["summary"][settings[0]]:
            row: list[Any] = [LABELS.get(m, m)]
            for s in settings:
                for r in refs:
                    row.append(f"{result['summary'][s][m]['ms_median'] / result['summary'][s][r]['ms_median']:.3f}")
            rows.append(row)
        out.append(md_table(head, rows))

    for variant, table in result.get("breakdown", {}).items():
        in_method = variant.split(" / ")[0]
        name = LABELS.get(in_method, in_method)
        out.append(f"\n## Where a registration's time goes ({name}, medians over pairs, ms)\n")
        out.append(
            "In-process: `Registration.timing_ms` of `core.pipeline.register`. HTTP: the server's `timing_ms` "
            "(decode = JSON parsing and base64 decoding) and the client's latency; HTTP/JSON overhead = client "
            "latency − server total, per pair (client encoding, transport, FastAPI, response JSON). `confidence`: "
            "the confidence of each ICP result (with exit checks, one per check)."
        )
        head = ["stage"] + [f"{where} ({s})" for s in settings for where in ("in-process", "HTTP")]
        stages = [
            "decode",
            "preprocess",
            "target_embedding",
            "agent_steps",
            "icp",
            "confidence",
            "rescue",
            "server total",
            "HTTP/JSON overhead",
            "total (client)",
            "agent steps run",
            "per agent step",
            "max abs ΔT vs in-process",
        ]
        rows = [[st] + [table[s][w].get(st, math.nan) for s in settings for w in ("in", "http")] for st in stages]
        out.append(md_table(head, rows))

    fl = result.get("flops")
    if fl:
        out.append("\n## Reward net: FLOPs and achieved GFLOP/s\n")
        best = max((r["gflops"] for r in result.get("sgemm", []) if r["threads"] == env["threads"]), default=math.nan)
        out.append(
            "FLOPs = 2 × multiply-adds of MatMul/Gemm/Conv nodes, counted from an onnxruntime profile of one call "
            "(unoptimised graph, concrete shapes); `target-only` = the part that depends on the target alone "
            "and is recomputed at every step. GFLOP/s over the measured median time; % of the best sgemm below "
            f"({fmt(best)} GFLOP/s at {env['threads']} threads)."
        )
        rows = []
        share = fl.get("head_step_share", 0.0)
        for label, flops, ms in (
            ("score.onnx, one call (a step after a rotation)", fl["score_flops"], fl["score_ms"]),
            ("head.onnx, one call (a step after a translation)", fl.get("head_flops", math.nan), fl.get("head_ms")),
            (
                f"agent step incl. Python (agent_steps / steps; {100 * share:.0f} % after a translation)",
                fl.get("agent_step_flops", fl["score_flops"]),
                fl["agent_step_ms"],
            ),
            ("embed.onnx (target, once per registration)", fl["embed_flops"], fl["embed_ms"]),
        ):
            if flops is None or not math.isfinite(flops):
                continue
            g = flops / ms / 1e6 if ms and math.isfinite(ms) else math.nan
            rows.append([label, flops / 1e6, ms, g, f"{100 * g / best:.0f}" if math.isfinite(best) else "-"])
        out.append(md_table(["what", "MFLOP", "ms", "GFLOP/s", "% of sgemm"], rows))
        share = fl["score_target_only_flops"] / fl["score_flops"] if fl["score_flops"] else math.nan
        ops = ", ".join(f"{k} {v / 1e6:.1f}" for k, v in sorted(fl["score_by_op"].items(), key=lambda kv: -kv[1]))
        out.append(
            f"\nscore.onnx MFLOP by op: {ops}. Target-only work inside score.onnx: "
            f"{fl['score_target_only_flops'] / 1e6:.1f} MFLOP per step ({100 * share:.0f} %)."
        )
    if result.get("sgemm"):
        out.append("\n## This CPU's sgemm (same run)\n")
        out.append(
            md_table(
                ["implementation", "n", "threads", "GFLOP/s"],
                [[r["impl"], str(r["n"]), str(r["threads"]), r["gflops"]] for r in result["sgemm"]],
            )
        )

    if result.get("ort_variants"):
        out.append("\n## onnxruntime session options: ms per score call (one agent step)\n")
        out.append(
            "Interleaved rounds (10 calls per variant each, variant order rotated, one variant's sessions open at a "
            "time) on one real state; `min` "
            "approximates the cost on an idle machine. `× default (best)`: median over rounds of this variant's best "
            "call ÷ the default's best call in the same round (the idle-machine comparison); `× default (median)`: "
            "the same with each round's median (how it fares on a busy machine). `embed`: the target embedding "
            "(median), once per request."
        )
        rows = [
            [
                v["variant"],
                v["score_ms"],
                v["score_min_ms"],
                v["score_p90_ms"],
                v["embed_ms"],
                f"{v['vs_default']:.2f}",
                f"{v['vs_default_busy']:.2f}",
            ]
            for v in result["ort_variants"]
        ]
        head = ["variant", "median ms", "min ms", "p90 ms", "embed ms", "× default (best)", "× default (median)"]
        out.append(md_table(head, rows))

    variants = result.get("variants", {})
    if variants and any(v["n"] for s in variants for v in variants[s].values()):
        out.append("\n## Early stop, int8 and head reuse against the default (fp32, all steps)\n")
        out.append(
            "Early stop: a scale ends when no action has a positive predicted reward. int8: dynamically "
            f"quantized graphs ({result.get('int8_source', '')}). No head reuse: every step runs score.onnx "
            "(the default re-scores a source that was only translated with head.onnx). v1 = agent only, "
            "v2 = agent + ICP."
        )
        rows = []
        for s in settings:
            base = result["summary"][s]
            for m, v in [(m, base[m]) for m in ("pranet-v1", "pranet-v2") if m in base] + list(variants[s].items()):
                if not v["n"]:
                    continue
                ref = base.get("pranet-v1" if "v1" in m else "pranet-v2")
                saving = 1 - v["ms_median"] / ref["ms_median"] if ref else math.nan
                rows.append(
                    [
                        s,
                        m,
                        v["ms_median"],
                        f"{100 * saving:+.0f}" if m not in base else "",
                        v.get("steps_mean", math.nan),
                        f"{100 * v['success']:.1f}",
                        v["rot_median"],
                        v["trans_median"],
                    ]
                )
        out.append(
            md_table(
                ["setting", "variant", "median ms", "time saved %", "steps", "success %", "rot° med", "trans med"], rows
            )
        )
    d = result.get("int8_drift")
    if d:
        out.append(
            f"\nint8 reward drift against fp32 on {d['states']} states along the fp32 agent's trajectories: "
            f"max |Δ| {d['max_abs']:.2e}, mean |Δ| {d['mean_abs']:.2e}, p99 {d['p99_abs']:.2e} (mean |reward| "
            f"{d['mean_abs_reward_fp32']:.3f}); same action chosen in {100 * d['argmax_agreement']:.1f} % of steps."
        )

    if result.get("throughput"):
        out.append("\n## Service throughput (pranet-serve, default requests = PRANet adaptive, concurrent clients)\n")
        rows = [
            [
                str(t["workers"]),
                str(t["threads_per_worker"]),
                str(t["clients"]),
                f"{t['seconds']:g}",
                str(t["completed"]),
                str(t["errors"]),
                t["per_s"],
                t["latency_ms"]["median"],
                t["latency_ms"]["p95"],
            ]
            for t in result["throughput"]
        ]
        out.append(
            md_table(
                [
                    "workers",
                    "ORT threads/worker",
                    "clients",
                    "seconds",
                    "completed",
                    "errors",
                    "registrations/s",
                    "median ms",
                    "p95 ms",
                ],
                rows,
            )
        )
    return "\n".join(out) + "\n"


def breakdown(
    records: Sequence[Record],
    settings: Sequence[str],
    in_method: str = "pranet-v2",
    http_method: str = "pranet-v2-http",
) -> dict[str, dict[str, dict[str, float]]]:
    out: dict[str, dict[str, dict[str, float]]] = {}
    for s in settings:
        inproc = [r for r in records if r.setting == s and r.method == in_method and r.error is None]
        http = [r for r in records if r.setting == s and r.method == http_method and r.error is None]
        stages = ("preprocess", "target_embedding", "agent_steps", "icp", "confidence", "rescue")
        b_in = {st: median([r.extra["timing_ms"].get(st, math.nan) for r in inproc]) for st in stages}
        b_in["total (client)"] = median([r.ms for r in inproc])
        b_in["agent steps run"] = median([r.extra["n_steps"] for r in inproc])
        b_in["per agent step"] = median(
            [r.extra["timing_ms"]["agent_steps"] / r.extra["n_steps"] for r in inproc if r.extra.get("n_steps")]
        )
        b_http = {
            st: median([r.extra["server_timing_ms"].get(st, math.nan) for r in http]) for st in ("decode", *stages)
        }
        b_http["server total"] = median([r.extra["server_timing_ms"]["total"] for r in http])
        b_http["HTTP/JSON overhead"] = median([r.ms - r.extra["server_timing_ms"]["total"] for r in http])
        b_http["total (client)"] = median([r.ms for r in http])
        # Same seed, same clouds (up to their float32 encoding): the service must return the in-process result.
        by_pair = {r.pair: r for r in inproc}
        b_http["max abs ΔT vs in-process"] = max(
            (
                float(np.abs(np.subtract(r.transform, by_pair[r.pair].transform)).max())
                for r in http
                if r.pair in by_pair and r.transform is not None and by_pair[r.pair].transform is not None
            ),
            default=math.nan,
        )
        out[s] = {"in": b_in, "http": b_http}
    return out


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Record):
        d = dict(o.__dict__)
        d["extra"] = {k: v for k, v in o.extra.items() if k != "agent_transform"}
        return d
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    command = shlex.join(["pranet-bench", *(sys.argv[1:] if argv is None else argv)])
    result = run(args, command)
    result["breakdown"] = {
        f"{a} / {b}": breakdown(result["records"], args.settings, a, b)
        for a, b in BREAKDOWN_PAIRS
        if a in args.methods and b in args.methods
    }
    text = report(result)
    print(text)
    if args.markdown is not None:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(f"```\n{command}\n```\n\n{text}")
        log(args, f"wrote {args.markdown}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        doc = json.loads(json.dumps(result, default=_json_default))  # records -> dicts first
        args.json.write_text(json.dumps(nan_to_none(doc), indent=1))
        log(args, f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
