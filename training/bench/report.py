"""The report: one markdown section per measurement."""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from collections.abc import Sequence
from typing import Any

import numpy as np

from pranet.core.metrics import SUCCESS_ROTATION_DEG, SUCCESS_TRANSLATION
from pranet.training.bench.catalog import REFERENCES
from pranet.training.bench.records import Record
from pranet.training.bench.tables import fmt, md_table, median
from pranet.training.reporting import json_default

LABELS = {
    "pranet-v1": "PRANet-v1 (agent, in-process)",
    "pranet-v2": "PRANet-v2 (agent + ICP, in-process)",
    "pranet-v2-http": "PRANet-v2 over HTTP (client side)",
    "pranet-adaptive": "PRANet adaptive (the service's default request, in-process)",
    "pranet-adaptive-http": "PRANet adaptive over HTTP (client side; the service's default)",
    "icp": "Open3D ICP (from identity)",
    "fgr-icp": "FGR + ICP",
    "ransac-icp": "RANSAC + ICP",
    "ransac-pranet-icp": "RANSAC + PRANet's ICP (the service's refinement)",
    "small-gicp": "small_gicp GICP (from identity)",
}


def _header(result: dict[str, Any]) -> list[str]:
    """The model, the machine and the pairs."""
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
    return out


def _latency(result: dict[str, Any]) -> list[str]:
    """Per setting and method: latency and success."""
    out: list[str] = []
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
    return out


def _ratios(result: dict[str, Any]) -> list[str]:
    """Each method's median latency as a ratio to the reference peers'."""
    out: list[str] = []
    settings = list(result["summary"])
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
    return out


def _as_dict(record: Record | dict[str, Any]) -> dict[str, Any]:
    """A record as a dict: the run passes ``Record`` objects, a JSON file dicts."""
    return dataclasses.asdict(record) if isinstance(record, Record) else record


def _status_flag(result: dict[str, Any]) -> list[str]:
    """How well each method's own ``status`` flags its failures: precision and recall of ``suspect``."""
    rows = []
    for setting in result["summary"]:
        for method in result["summary"][setting]:
            recs = [
                r
                for r in map(_as_dict, result.get("records", []))
                if r["setting"] == setting and r["method"] == method and (r.get("extra") or {}).get("status")
            ]
            if not recs:
                continue
            failed = np.array([not r["success"] for r in recs])
            suspect = np.array([r["extra"]["status"] == "suspect" for r in recs])
            hits = int(np.sum(failed & suspect))
            precision = hits / suspect.sum() if suspect.any() else math.nan
            recall = hits / failed.sum() if failed.any() else math.nan
            won = Counter(r["extra"].get("candidate") for r in recs)
            rows.append(
                [
                    setting,
                    LABELS.get(method, method),
                    len(recs),
                    int(failed.sum()),
                    int(suspect.sum()),
                    precision,
                    recall,
                ]
                + [", ".join(f"{k} {v}" for k, v in sorted(won.items(), key=lambda kv: -kv[1]) if k)]
            )
    if not rows:
        return []
    head = ["setting", "method", "pairs", "failures", "suspect", "suspect precision", "suspect recall", "winner"]
    return [
        "\n## The status flag: precision and recall of `suspect` for failures (same success criterion)\n",
        md_table(head, rows),
    ]


def _breakdowns(result: dict[str, Any]) -> list[str]:
    """Where a registration's time goes, in-process and over HTTP."""
    out: list[str] = []
    settings = list(result["summary"])
    for variant, table in result.get("breakdown", {}).items():
        in_method = variant.split(" / ")[0]
        name = LABELS.get(in_method, in_method)
        out.append(f"\n## Where a registration's time goes ({name}, medians over pairs, ms)\n")
        out.append(
            "In-process: `Registration.timing_ms` of `core.pipeline.register`. HTTP: the server's `timing_ms` "
            "(decode = JSON parsing and base64 decoding) and the client's latency; HTTP/JSON overhead = client "
            "latency − server total, per pair (client encoding, transport, FastAPI, response JSON). `confidence`: "
            "the confidence of each ICP result (with exit checks, one per check). `network calls`: source poses "
            "the reward network scored (full evaluations)."
        )
        head = ["stage"] + [f"{where} ({s})" for s in settings for where in ("in-process", "HTTP")]
        stages = [
            "decode",
            "preprocess",
            "target_embedding",
            "agent_steps",
            "icp",
            "confidence",
            "global_match",
            "rescue",
            "polish",
            "other",
            "server total",
            "HTTP/JSON overhead",
            "total (client)",
            "agent steps run",
            "network calls",
            "per agent step",
            "max abs ΔT vs in-process",
        ]
        rows = [[st] + [table[s][w].get(st, math.nan) for s in settings for w in ("in", "http")] for st in stages]
        out.append(md_table(head, rows))
    return out


def _flops(result: dict[str, Any]) -> list[str]:
    """The reward net's FLOPs and achieved GFLOP/s."""
    out: list[str] = []
    env = result["environment"]
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
        share, fine_share = fl.get("head_step_share", 0.0), fl.get("fine_step_share", 0.0)
        match_share = fl.get("match_step_share", 0.0)
        for label, flops, ms in (
            ("score.onnx, one call (a step after a rotation)", fl["score_flops"], fl["score_ms"]),
            ("head.onnx, one call (a step after a translation)", fl.get("head_flops", math.nan), fl.get("head_ms")),
            ("score_fine.onnx, one call (a fine-phase step)", fl.get("fine_flops", math.nan), fl.get("fine_ms")),
            (
                "match_fine.onnx, one call (a fine-phase step after a translation)",
                fl.get("match_flops", math.nan),
                fl.get("match_ms"),
            ),
            (
                f"agent step incl. Python (agent_steps / steps; {100 * share:.0f} % by head.onnx after a "
                f"translation, {100 * fine_share:.0f} % by score_fine.onnx, {100 * match_share:.0f} % by "
                "match_fine.onnx)",
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
    return out


def _sgemm(result: dict[str, Any]) -> list[str]:
    """This CPU's sgemm, the ceiling of the GFLOP/s above."""
    out: list[str] = []
    if result.get("sgemm"):
        out.append("\n## This CPU's sgemm (same run)\n")
        out.append(
            md_table(
                ["implementation", "n", "threads", "GFLOP/s"],
                [[r["impl"], str(r["n"]), str(r["threads"]), r["gflops"]] for r in result["sgemm"]],
            )
        )
    return out


def _ort_options(result: dict[str, Any]) -> list[str]:
    """Per-call latency of onnxruntime session options."""
    out: list[str] = []
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
    return out


def _variants(result: dict[str, Any]) -> list[str]:
    """Early stop, int8 and head reuse against the default; the int8 drift."""
    out: list[str] = []
    settings = list(result["summary"])
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
    return out


def _throughput(result: dict[str, Any]) -> list[str]:
    """Registrations per second of the service."""
    out: list[str] = []
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
    return out


def report(result: dict[str, Any]) -> str:
    """The markdown report: one section per measurement, those the run made."""
    sections = (
        _header,
        _latency,
        _ratios,
        _status_flag,
        _breakdowns,
        _flops,
        _sgemm,
        _ort_options,
        _variants,
        _throughput,
    )
    return "\n".join(line for section in sections for line in section(result)) + "\n"


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
        stages = (
            "preprocess",
            "target_embedding",
            "agent_steps",
            "icp",
            "confidence",
            "global_match",
            "rescue",
            "polish",
        )
        b_in = {st: median([r.extra["timing_ms"].get(st, math.nan) for r in inproc]) for st in stages}
        b_in["total (client)"] = median([r.ms for r in inproc])
        b_in["agent steps run"] = median([r.extra["n_steps"] for r in inproc])
        b_in["network calls"] = median([r.extra.get("network_calls", math.nan) for r in inproc])
        b_in["per agent step"] = median(
            [r.extra["timing_ms"]["agent_steps"] / r.extra["n_steps"] for r in inproc if r.extra.get("n_steps")]
        )
        b_http = {
            st: median([r.extra["server_timing_ms"].get(st, math.nan) for r in http]) for st in ("decode", *stages)
        }
        b_http["server total"] = median([r.extra["server_timing_ms"]["total"] for r in http])
        b_http["HTTP/JSON overhead"] = median([r.ms - r.extra["server_timing_ms"]["total"] for r in http])
        b_http["total (client)"] = median([r.ms for r in http])
        b_http["network calls"] = median([r.extra.get("network_calls") or math.nan for r in http])
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
    """``reporting.json_default``, plus records (without their transforms)."""
    if isinstance(o, Record):
        d = dict(o.__dict__)
        d["extra"] = {k: v for k, v in o.extra.items() if k != "agent_transform"}
        return d
    return json_default(o)
