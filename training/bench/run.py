"""``pranet-bench``'s arguments and the run itself: every method on the same pairs, interleaved."""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from pranet.training.bench.catalog import DEFAULT_SETTINGS, METHODS
from pranet.training.bench.drift import DriftScorer, drift_summary
from pranet.training.bench.flops import flops_table, sgemm_table, unit_clouds
from pranet.training.bench.methods import (
    MethodFn,
    Outcome,
    baseline_method,
    http_method,
    pranet_method,
    refined_by,
    request_body,
    small_gicp_align,
)
from pranet.training.bench.ort import ort_variants_table
from pranet.training.bench.records import Record, as_float32, pair_seed, score_pair, summarize
from pranet.training.bench.server import served, server_settings, throughput
from pranet.training.reporting import environment
from pranet.training.samples import SETTINGS, Pair, make_pair, pair_rng


def package_doc() -> str:
    from pranet.training import bench

    return (bench.__doc__ or "").split("\n\n")[0]


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="pranet-bench",
        description=package_doc(),
        epilog="See docs/PERFORMANCE.md for the method and the measured tables. The real-scan benchmark is a "
        "subcommand: pranet-bench scans [PAIRS.csv] (pranet-bench scans --help).",
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


def bench_pairs(args: argparse.Namespace) -> dict[str, list[Pair]]:
    """The unseen-category pairs of each setting, as every method sees them (float32 clouds)."""
    from pranet.training.data import data_dir, load_modelnet40, test_indices

    data = load_modelnet40(data_dir(args.data_dir), "test")
    idx = test_indices(data.labels)[: args.pairs]
    return {
        s: [as_float32(make_pair(data.points[j], s, pair_rng(args.seed, s, i), 60.0, 0.5)) for i, j in enumerate(idx)]
        for s in args.settings
    }


def int8_model(args: argparse.Namespace, model_dir: Path, tmp: Path) -> tuple[Path | None, str]:
    """The int8 graphs to time: the model directory's own, else quantized now into a temporary copy."""
    from pranet.engine.runtime import read_card

    if not (args.int8 or args.ort_calls > 0):
        return None, ""
    try:
        read_card(model_dir, precision="int8")
        return model_dir, "the model directory's int8 graphs"
    except Exception:
        from pranet.model.quantize import quantize_model_dir

        int8_dir = tmp / "model-int8"
        shutil.copytree(model_dir, int8_dir)
        quantize_model_dir(int8_dir)
        return int8_dir, "quantized in this run (pranet-export --int8) into a temporary copy"


@dataclass
class MethodSet:
    """The methods of the latency table (``main``) and the variants measured beside them (``extra``)."""

    main: dict[str, MethodFn]
    extra: dict[str, MethodFn]
    scorer_full: Any  # every step through score.onnx: the FLOPs table's scorer
    drift: DriftScorer | None
    paper_fine_call: bool = False  # PAPER_V2 takes the model's fine-phase call: so does its request over HTTP


def build_methods(args: argparse.Namespace, engine: Any, model_dir: Path, int8_dir: Path | None) -> MethodSet:
    from pranet.core.registration_config import PAPER_V1, PAPER_V2, SERVICE_DEFAULT
    from pranet.engine.engine import Engine
    from pranet.engine.runtime import RewardModel
    from pranet.training import baselines

    steps = {"schedule": tuple(args.steps) if args.steps else None}
    v1, v2 = PAPER_V1.with_(**steps), PAPER_V2.with_(**steps)
    main = {
        "pranet-v1": pranet_method(engine, v1),
        "pranet-v2": pranet_method(engine, v2),
        "pranet-adaptive": pranet_method(engine, SERVICE_DEFAULT.with_(**steps)),
        "icp": baseline_method(baselines.icp),
        "fgr-icp": baseline_method(baselines.fgr_icp),
        "ransac-icp": baseline_method(baselines.ransac_icp),
        "ransac-pranet-icp": baseline_method(refined_by(baselines.ransac, engine.icp(v2.icp_stages))),
        "small-gicp": baseline_method(
            lambda s, t, rng: small_gicp_align(s, t, baselines.ICP_MAX_DISTANCE, args.threads)
        ),
    }
    # No head-only re-scoring of translated sources (every trained-call step through score.onnx): what that reuse
    # buys. With the fine phase's call only the coarse phase reuses.
    scorer_full = RewardModel.load(model_dir, threads=args.threads, reuse_translations=False)
    extra = {"pranet-full": pranet_method(Engine(scorer_full), v2)}
    if args.early_stop:
        extra["pranet-es"] = pranet_method(engine, v2.with_(early_stop=True))
    drift: DriftScorer | None = None
    if args.int8 and int8_dir is not None:
        scorer8 = RewardModel.load(int8_dir, threads=args.threads, precision="int8")
        extra["pranet-int8"] = pranet_method(Engine(scorer8), v2)
        drift = DriftScorer(engine.scorer, scorer8)
        extra["drift"] = pranet_method(Engine(drift), v1)
    return MethodSet(main, extra, scorer_full, drift, v2.uses_fine_call(engine.scorer.has_fine_call))


def run_interleaved(
    args: argparse.Namespace, pairs: dict[str, list[Pair]], methods: MethodSet, tmp: Path, t_start: float
) -> tuple[list[Record], list[str]]:
    """Every method on every pair, their order rotated per pair, the HTTP ones through a real server.
    Returns the records and the order of the methods."""
    import httpx

    records: list[Record] = []
    fns = methods.main
    with served(server_settings(args.model, args.threads, 1, "fp32"), tmp) as server:
        client = httpx.Client(base_url=server.url, timeout=120.0)
        if "pranet-v2-http" in args.methods:
            fns["pranet-v2-http"] = http_method(client, args.steps, fine_matching=methods.paper_fine_call)
        if "pranet-adaptive-http" in args.methods:
            fns["pranet-adaptive-http"] = http_method(client, args.steps, adaptive=True)
        order = [m for m in args.methods if m in fns] + list(methods.extra)
        allfns = {**fns, **methods.extra}
        warm = pairs[args.settings[0]][0]
        for m in order:  # first calls: imports, allocations, connections
            allfns[m](warm, 0)
        if methods.drift is not None:
            methods.drift.pairs.clear()
        total, done = len(args.settings) * args.pairs, 0
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
    return records, order


VARIANT_TAGS = {"pranet-es": "early stop", "pranet-int8": "int8", "pranet-full": "no head reuse"}


def variant_records(records: list[Record], pairs: dict[str, list[Pair]]) -> list[Record]:
    """Early stop, int8 and no-reuse ran agent + ICP once per pair: v2 is that run, v1 its agent result (minus
    the ICP time)."""
    derived: list[Record] = []
    for r in records:
        if r.method not in VARIANT_TAGS:
            continue
        tag = VARIANT_TAGS[r.method]
        if r.error is not None:
            derived += [replace(r, method=f"pranet-v1 {tag}"), replace(r, method=f"pranet-v2 {tag}")]
            continue
        v1 = Outcome(r.extra["agent_transform"], r.ms - r.extra["timing_ms"].get("icp", 0.0), r.extra)
        derived += [score_pair(f"pranet-v1 {tag}", r.setting, r.pair, pairs[r.setting][r.pair], v1, None)]
        derived += [replace(r, method=f"pranet-v2 {tag}")]
    return derived


def service_throughput(args: argparse.Namespace, pairs: dict[str, list[Pair]], tmp: Path) -> list[dict[str, Any]]:
    """Registrations per second with 1 and 2 workers, the service's default request, concurrent clients."""
    bodies = [  # the service's default request: exit checks and rescue
        request_body(p, pair_seed(args.seed, args.settings[0], i), steps=args.steps, adaptive=True)
        for i, p in enumerate(pairs[args.settings[0]][:8])
    ]
    rows = []
    for w in args.workers:
        t_per = max(1, args.threads // w)
        log(args, f"throughput: {w} worker(s) x {t_per} thread(s), {args.clients} clients")
        with served(server_settings(args.model, t_per, w, "fp32"), tmp) as server:
            tp = throughput(server.url, bodies, args.clients, args.throughput_seconds)
        rows.append({"workers": w, "threads_per_worker": t_per, **tp})
    return rows


def run(args: argparse.Namespace, command: str) -> dict[str, Any]:
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))  # Open3D reads it at import
    # OpenMP threads (Open3D, small_gicp) that busy-wait at barriers collapse when a core is taken by another
    # process: small_gicp with 2 threads measured 800 ms instead of 4 ms per pair beside a training run.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from pranet.engine.engine import Engine
    from pranet.engine.runtime import default_model_dir

    t_start = time.perf_counter()
    result: dict[str, Any] = {"command": command, "environment": environment(args.threads)}
    result["config"] = {k: v for k, v in vars(args).items() if k not in ("markdown", "json", "quiet")}
    # 1. The pairs and the model.
    pairs = bench_pairs(args)
    model_dir = Path(args.model) if args.model else default_model_dir()
    engine = Engine.load(model_dir, threads=args.threads)
    scorer = engine.scorer
    result["model"] = {**scorer.info(), "dir": str(args.model or "default (shipped)")}
    result["model_schedule"] = list(scorer.schedule)
    tmp = Path(tempfile.mkdtemp(prefix="pranet-bench-"))
    try:
        # 2. The methods, then every method on every pair, side by side.
        int8_dir, result["int8_source"] = int8_model(args, model_dir, tmp)
        methods = build_methods(args, engine, model_dir, int8_dir)
        records, order = run_interleaved(args, pairs, methods, tmp, t_start)
        result["summary"] = {
            s: {
                m: summarize([r for r in records if r.setting == s and r.method == m])
                for m in order
                if m in methods.main
            }
            for s in args.settings
        }
        # 3. The variants (early stop, int8, no head reuse), as v1 and v2 rows.
        derived = variant_records(records, pairs)
        variants = [f"pranet-{v} {tag}" for tag in VARIANT_TAGS.values() for v in ("v1", "v2")]
        result["variants"] = {
            s: {m: summarize([r for r in derived if r.setting == s and r.method == m]) for m in variants}
            for s in args.settings
        }
        records += derived
        if methods.drift is not None:
            result["int8_drift"] = drift_summary(methods.drift.pairs, scorer.table, args.steps or scorer.schedule)
        # 4. Per-step costs, FLOPs, sgemm, onnxruntime options, throughput.
        src_u, tgt_u = unit_clouds(pairs[args.settings[0]][0], scorer.n_points, args.seed)
        result["flops"] = flops_table(model_dir, methods.scorer_full, src_u, tgt_u, records)
        result["sgemm"] = sgemm_table(args.threads)
        if args.ort_calls > 0:
            log(args, "onnxruntime options")
            result["ort_variants"] = ort_variants_table(
                args.model, int8_dir, args.threads, src_u, tgt_u, args.ort_calls
            )
        if args.throughput_seconds > 0:
            result["throughput"] = service_throughput(args, pairs, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    result["records"] = records
    result["wall_s"] = time.perf_counter() - t_start
    return result
