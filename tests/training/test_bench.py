"""pranet-bench end to end at a tiny size: every method and section in the tables, finite numbers.

Timings are not asserted (the machine is shared); only that the benchmark runs and reports them.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

pytest.importorskip("open3d")
pytest.importorskip("small_gicp")
pytest.importorskip("httpx")

from pranet.training import bench  # noqa: E402


def _rows(text: str, section: str) -> list[list[str]]:
    """Cells of the data rows of the markdown table under ``## section`` (header left out)."""
    block = text.split(f"## {section}", 1)[1].split("\n## ", 1)[0]
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in block.splitlines() if line.startswith("| ")]
    return rows[1:]


def _finite(cell: str) -> bool:
    try:
        return math.isfinite(float(cell))
    except ValueError:
        return False


@pytest.fixture(scope="module")
def bench_run(data_root, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    argv = [
        "--pairs", "1",
        "--settings", "noisy,partial",
        "--steps", "2,2",
        "--ort-calls", "11",
        "--throughput-seconds", "1",
        "--workers", "1",
        "--clients", "2",
        "--data-dir", str(data_root),
        "--markdown", str(out / "bench.md"),
        "--json", str(out / "bench.json"),
        "--quiet",
    ]  # fmt: skip
    assert bench.main(argv) == 0
    return (out / "bench.md").read_text(), json.loads((out / "bench.json").read_text()), argv


def test_every_method_has_finite_latency_and_a_success_rate(bench_run):
    text, doc, argv = bench_run
    assert text.startswith("```\npranet-bench ") and "--pairs 1" in text.splitlines()[1]
    rows = _rows(text, "Latency and success")
    for setting in ("noisy", "partial"):
        for method in bench.METHODS:
            row = next(r for r in rows if r[0] == setting and r[1] == bench.LABELS[method])
            assert row[2] == "1" and row[8] == "0", row  # one pair, no error
            assert all(_finite(c) for c in row[3:6]), row  # median, p95, success %
            s = doc["summary"][setting][method]
            assert s["ms_median"] > 0 and 0.0 <= s["success"] <= 1.0
    ratios = _rows(text, "Median latency relative to RANSAC+ICP and FGR+ICP")
    assert {r[0] for r in ratios} == {bench.LABELS[m] for m in bench.METHODS}
    assert all(_finite(c) for r in ratios for c in r[1:])
    # Every ratio is the two medians of the raw summary divided (an independent recomputation of the table).
    settings = list(doc["summary"])
    for r in ratios:
        method = next(m for m in doc["summary"][settings[0]] if bench.LABELS.get(m, m) == r[0])
        expected = [
            doc["summary"][s][method]["ms_median"] / doc["summary"][s][ref]["ms_median"]
            for s in settings
            for ref in ("ransac-icp", "fgr-icp")
        ]
        np.testing.assert_allclose([float(c) for c in r[1:]], expected, rtol=2e-3, atol=1e-3)


def test_breakdown_flops_ort_int8_early_stop_and_throughput_are_reported(bench_run):
    text, doc, _ = bench_run
    breakdown = {r[0]: r[1:] for r in _rows(text, "Where a registration's time goes")}
    for stage in ("preprocess", "target_embedding", "agent_steps", "icp", "total (client)"):
        assert _finite(breakdown[stage][0]) and _finite(breakdown[stage][1]), stage
    assert _finite(breakdown["HTTP/JSON overhead"][1]) and _finite(breakdown["decode"][1])
    assert _finite(breakdown["agent steps run"][0]) and _finite(breakdown["confidence"][0])
    # The service returns what register() returns in-process for the same seed (clouds sent as float32),
    # for the paper's v2 and for the adaptive variant (the service's default request).
    assert set(doc["breakdown"]) == {"pranet-v2 / pranet-v2-http", "pranet-adaptive / pranet-adaptive-http"}
    for table in doc["breakdown"].values():
        assert table["noisy"]["http"]["max abs ΔT vs in-process"] < 1e-3
    assert text.count("## Where a registration's time goes") == 2

    flops = doc["flops"]
    assert flops["score_flops"] > 1e6 and 0 < flops["score_target_only_flops"] < flops["score_flops"]
    # The shipped model has head.onnx: a step after a translation costs the MLP heads alone.
    assert 0 < flops["head_flops"] < flops["score_flops"] / 20
    # And the paper's fine phase goes through the model's fine-phase call: here 2 of 2 + 2 steps, each by
    # score_fine.onnx or, after a fine translation, by match_fine.onnx (the matching alone: fewer FLOPs).
    fine_share, match_share = flops["fine_step_share"], flops["match_step_share"]
    assert fine_share + match_share == 0.5 and fine_share > 0 and match_share > 0
    assert flops["fine_flops"] > 1e6 and _finite(flops["fine_ms"])
    assert 0 < flops["match_flops"] < flops["fine_flops"] and _finite(flops["match_ms"])
    assert flops["head_flops"] <= flops["agent_step_flops"] <= max(flops["score_flops"], flops["fine_flops"])
    assert 0.0 <= flops["head_step_share"] <= 1.0 - fine_share - match_share
    assert all(_finite(c) for r in _rows(text, "Reward net") for c in r[1:4])
    sgemm = _rows(text, "This CPU's sgemm")
    assert {r[0] for r in sgemm} >= {"numpy float32 matmul"} and all(float(r[3]) > 0 for r in sgemm)

    variants = {r[0]: r for r in _rows(text, "onnxruntime session options")}
    assert len(variants) == len(bench.ORT_VARIANTS) and "int8" in variants
    assert all(_finite(c) for r in variants.values() for c in r[1:5])

    names = {r[1] for r in _rows(text, "Early stop, int8 and head reuse")}
    assert names >= {f"pranet-{v} {t}" for v in ("v1", "v2") for t in ("early stop", "int8", "no head reuse")}
    # Re-scoring translated sources with the head alone changes no decision: same result as every step in full.
    for s in ("noisy", "partial"):
        full, reused = doc["variants"][s]["pranet-v2 no head reuse"], doc["summary"][s]["pranet-v2"]
        assert full["rot_median"] == pytest.approx(reused["rot_median"], abs=1e-6)
    drift = doc["int8_drift"]
    assert drift["states"] == 2 * 4 and 0 <= drift["mean_abs"] <= drift["max_abs"] < 0.05
    # int8 drift of at most 0.05 on unit-normalised rewards cannot flip most decisions: the agent sees the same
    # best action in most steps (a broken quantization, or comparing the wrong graphs, lands far below).
    assert drift["argmax_agreement"] >= 0.7, drift

    (tp,) = doc["throughput"]
    assert tp["workers"] == 1 and tp["errors"] == 0
    # Requests answered per second agree with the count and the wall time the run measured.
    assert (
        tp["completed"] >= 1
        and tp["per_s"] > 0
        and tp["per_s"] == pytest.approx(tp["completed"] / tp["seconds"], rel=1e-6)
    ), tp


def test_flop_count_of_a_known_matmul():
    assert bench.node_flops("MatMul", [[1, 256, 64], [64, 128]], [[1, 256, 128]]) == 2 * 256 * 64 * 128
    assert bench.node_flops("Gemm", [[1, 256], [128, 256]], [[1, 128]]) == 2 * 256 * 128
    assert bench.node_flops("Relu", [[10]], [[10]]) == 0
    assert bench.median([1.0, float("nan"), 3.0]) == 2.0 and np.isnan(bench.median([]))
    assert re.fullmatch(r"\| a +\| b +\|\n\|-+\|-+\|\n\| 1 +\| x +\|", bench.md_table(["a", "b"], [[1.0, "x"]]))


def test_refined_by_runs_the_service_icp_in_the_unit_frame_and_returns_world_units():
    """A coarse estimate 4° and 2 cm off on a 100x-scaled shape: the refinement must reach the truth in the
    clouds' own units (a unit-frame transform returned as is would keep a 100x too small translation)."""
    from scipy.spatial.transform import Rotation

    from pranet.core.metrics import isotropic_errors
    from pranet.engine.icp import make_icp

    rng = np.random.default_rng(0)
    u = rng.standard_normal((1500, 3))
    shape = u / np.linalg.norm(u, axis=1, keepdims=True) * [90.0, 60.0, 40.0] + [300.0, -50.0, 20.0]
    R = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
    t = np.array([12.0, -7.0, 3.0])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    source, target = shape[:1000], shape[500:] @ R.T + t
    off = np.eye(4)
    off[:3, :3], off[:3, 3] = Rotation.from_rotvec([0.0, np.deg2rad(4.0), 0.0]).as_matrix(), [2.0, 0.0, 0.0]
    coarse = lambda s, g, r: T @ off  # noqa: E731
    rot0, trans0 = isotropic_errors(coarse(source, target, rng), T)
    rot, trans = isotropic_errors(bench.refined_by(coarse, make_icp())(source, target, rng), T)
    assert rot0 > 3.9 and rot < 0.3 and trans < 1.0 < trans0, (rot0, trans0, rot, trans)  # unit-frame t: ~14 off


def test_onnxruntime_table_times_score_onnx_not_the_head(bench_run):
    """The table calls score_fn on one unchanged source; with head reuse on, every call after the first would
    run head.onnx only (0.1 ms instead of ~5 ms) and the table would time the MLP heads."""
    _, doc, _ = bench_run
    assert doc["ort_variants"], "no onnxruntime variants measured"
    for row in doc["ort_variants"]:
        assert row["graph_calls"]["head"] == 0 and row["graph_calls"]["full"] >= row["calls"], row
