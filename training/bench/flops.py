"""FLOPs of the reward net (from an onnxruntime profile) against this CPU's sgemm throughput."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pranet.core.se3 import Array
from pranet.training.bench.records import Record
from pranet.training.bench.tables import median
from pranet.training.samples import Pair


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


def unit_clouds(pair: Pair, n_points: int, seed: int) -> tuple[Array, Array]:
    """The pair as ``register`` hands it to the model: normalised to the unit frame, resampled to N points."""
    from pranet.core.preprocess import check_cloud, fit_normalization, resample

    src, tgt = check_cloud(pair.source, "source"), check_cloud(pair.target, "target")
    norm = fit_normalization(src, tgt)
    rng = np.random.default_rng(seed)
    return resample(norm.to_unit(src), n_points, rng), resample(norm.to_unit(tgt), n_points, rng)


def times_ms(call: Any, n: int) -> list[float]:
    """Wall times of ``n`` calls of ``call()``, in milliseconds."""
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        call()
        out.append((time.perf_counter() - t0) * 1e3)
    return out


def flops_table(model_dir: Path, scorer: Any, source: Array, target: Array, records: Sequence[Record]) -> dict:
    """FLOPs per call of the graphs, the measured time per call and per agent step, the achieved GFLOP/s.

    ``scorer`` must not reuse pair features (``reuse_translations=False``): the timed calls repeat one pose.
    An agent step's FLOPs average score.onnx, head.onnx, score_fine.onnx and match_fine.onnx calls by the shares of
    the steps each scored in the pranet-v1 records (``methods.steps_by_graph``: head.onnx re-scores a step after a
    translation, score_fine.onnx the fine phase where the paper's configuration takes it, match_fine.onnx a fine
    step after a fine translation).
    """
    from pranet.core.knn import knn_indices
    from pranet.engine.runtime import FINE_GRAPH, HEAD_GRAPH, graph_files

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
    twin = scorer.twin_term(pts[0], score_feeds["knn"][0], tpts[0], tknn[0])
    if twin is not None:
        score_feeds["twin"] = twin
    fl_score = graph_flops(model_dir / score_file, score_feeds)
    fl_embed = graph_flops(model_dir / embed_file, {"points": tpts, "knn": tknn})
    f = scorer.score_fn(target)
    f(source, target)
    score_ms = times_ms(lambda: f(source, target), 50)
    embed_ms = times_ms(lambda: scorer.embed(tpts), 10)
    head_ms: list[float] = []
    head_flops = math.nan
    if (model_dir / HEAD_GRAPH).is_file():
        import onnxruntime as ort

        full = ort.InferenceSession(str(model_dir / score_file), providers=["CPUExecutionProvider"])
        pair = full.run(["pair_features"], {i.name: score_feeds[i.name] for i in full.get_inputs()})[0]
        head_feeds = {"pair_features": pair, "offset": np.zeros((1, 3), np.float32)}
        head_flops = graph_flops(model_dir / HEAD_GRAPH, head_feeds)["flops"]
        head = ort.InferenceSession(str(model_dir / HEAD_GRAPH), providers=["CPUExecutionProvider"])
        head_ms = times_ms(lambda: head.run(None, head_feeds), 50)
    v1 = [r for r in records if r.method == "pranet-v1" and r.error is None and r.extra.get("n_steps")]
    step_ms = median([r.extra["timing_ms"]["agent_steps"] / r.extra["n_steps"] for r in v1])
    n_steps = max(1, sum(r.extra["n_steps"] for r in v1))
    share = sum(r.extra.get("after_translation", 0) for r in v1) / n_steps
    fine_share = sum(r.extra.get("fine_steps", 0) for r in v1) / n_steps
    match_share = sum(r.extra.get("match_steps", 0) for r in v1) / n_steps
    fine_flops, fine_ms = 0.0, []
    if (fine_share or match_share) and f.fine is not None:
        fine_flops = graph_flops(model_dir / FINE_GRAPH, score_feeds)["flops"]
        fine_ms = times_ms(lambda: f.fine(source, target), 20)
    match_flops, match_ms = match_graph_cost(model_dir, scorer, score_feeds) if match_share else (0.0, [])
    head_part = 0.0 if math.isnan(head_flops) else share * head_flops
    score_share = 1 - fine_share - match_share - (0.0 if math.isnan(head_flops) else share)
    step_flops = score_share * fl_score["flops"] + head_part + fine_share * fine_flops + match_share * match_flops
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
        "fine_flops": fine_flops if fine_ms else math.nan,
        "fine_ms": median(fine_ms) if fine_ms else math.nan,
        "fine_step_share": fine_share,
        "match_flops": match_flops if match_ms else math.nan,
        "match_ms": median(match_ms) if match_ms else math.nan,
        "match_step_share": match_share,
    }


def match_graph_cost(model_dir: Path, scorer: Any, score_feeds: dict[str, Array]) -> tuple[float, list[float]]:
    """``match_fine.onnx``'s FLOPs and call times (ms) on the matching inputs ``score_fine.onnx`` returns for
    ``score_feeds``' source, translated: the fine phase's step after a translation. Timed in ``scorer``'s own
    session (its thread count), as the fine call is."""
    import onnxruntime as ort

    from pranet.engine.runtime import FINE_GRAPH, FINE_MATCH_GRAPH

    fine = ort.InferenceSession(str(model_dir / FINE_GRAPH), providers=["CPUExecutionProvider"])
    feeds = {i.name: score_feeds[i.name] for i in fine.get_inputs()}
    similarity, params = fine.run(["similarity", "match_params"], feeds)
    match_feeds = {
        "points": score_feeds["points"] + np.float32(0.01),
        "target_points": score_feeds["target_points"],
        "target_centroid": score_feeds["target_centroid"],
        "similarity": similarity,
        "match_params": params,
    }
    session = scorer._match or ort.InferenceSession(
        str(model_dir / FINE_MATCH_GRAPH), providers=["CPUExecutionProvider"]
    )
    return graph_flops(model_dir / FINE_MATCH_GRAPH, match_feeds)["flops"], times_ms(
        lambda: session.run(None, match_feeds), 20
    )


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
