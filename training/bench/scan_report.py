"""The report of ``pranet-bench scans``: a summary line per method, the pairs, and a row per pair and method."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pranet.training.bench.scan_peers import PEERS
from pranet.training.bench.tables import fmt, md_table, median

SECTION = "## Real scans"
LABELS = {
    "pranet": "PRANet, the service's default request (in process)",
    "pranet-http": "PRANet, the service's default request over HTTP",
    "open3d-ransac-icp": "Open3D FPFH + RANSAC + point-to-plane ICP",
    "kiss-matcher-gicp": "KISS-Matcher + small_gicp GICP",
    "fgr-icp": "Open3D FPFH + FGR + point-to-plane ICP",
}


def _ratio(part: int, whole: int) -> float:
    return part / whole if whole else math.nan


def suspect_scores(records: Sequence[Any]) -> tuple[float, float]:
    """Precision and recall of ``status == "suspect"`` as a detector of wrong results, over the records that carry
    a status (nan where undefined: no suspect result, or no wrong one)."""
    rated = [r for r in records if r.status is not None]
    flagged = [r for r in rated if r.status == "suspect"]
    wrong = [r for r in rated if not r.right]
    caught = [r for r in flagged if not r.right]
    return _ratio(len(caught), len(flagged)), _ratio(len(caught), len(wrong))


def summarize(records: Sequence[Any], methods: Sequence[str]) -> dict[str, dict[str, Any]]:
    """Per method: right n/N, median errors on object pairs, median latency and its ratio to the fastest peer's,
    how many ``converged``, and the precision and recall of ``suspect`` for wrong results."""
    out: dict[str, dict[str, Any]] = {}
    for m in methods:
        rs = [r for r in records if r.method == m]
        ok = [r for r in rs if r.error is None]
        objects = [r for r in ok if r.category == "object"]
        rated = [r for r in rs if r.status is not None]
        precision, recall = suspect_scores(rs)
        out[m] = {
            "n": len(rs),
            "right": sum(r.right for r in rs),
            "errors": len(rs) - len(ok),
            "object_pairs": len(objects),
            "rot_median_object": median([r.rotation_deg for r in objects]),
            "trans_median_object": median([r.translation for r in objects]),
            "ms_median": median([r.ms for r in ok]),
            "converged": sum(r.status == "converged" for r in rated) if rated else None,
            "rated": len(rated),
            "suspect_precision": precision,
            "suspect_recall": recall,
        }
    peer_ms = {m: out[m]["ms_median"] for m in methods if m in PEERS and math.isfinite(out[m]["ms_median"])}
    fastest = min(peer_ms, key=peer_ms.__getitem__) if peer_ms else None
    for m in methods:
        out[m]["fastest_peer"] = fastest
        out[m]["ms_ratio_fastest_peer"] = out[m]["ms_median"] / peer_ms[fastest] if fastest else math.nan
    return out


def _header(result: dict[str, Any]) -> list[str]:
    env, cfg = result["environment"], result["config"]
    model = result.get("model")
    lines = [
        f"`{result['command']}`",
        "",
        f"{len(result['pairs'])} pairs from `{cfg['pairs_csv']}`, every method on every pair in one run (their order "
        f"rotated pair by pair), {cfg['threads']} thread(s) per method, seed {cfg['seed']}. CPU: {env['cpu']}, "
        f"{env['cpu_count']} cores, load average {fmt(env.get('load_avg_1m'))} at the start (the machine is shared: "
        f"compare latencies within this run, not with other runs). Wall time {result['wall_s']:.0f} s.",
    ]
    versions = ", ".join(
        f"{k} {env.get(k)}" for k in ("open3d-cpu", "open3d", "small_gicp", "kiss_matcher") if env.get(k)
    )
    if model:
        lines[-1] += f" Model: {model.get('name')} {model.get('version')} (sha256 {str(model.get('sha256'))[:12]})."
    lines[-1] += f" {versions}."
    obj, scene = cfg["thresholds"]["object"], cfg["thresholds"]["scene"]
    lines += [
        "",
        f"Right: rotation error < {fmt(obj['rotation_deg'])}° and translation error < {fmt(obj['translation'])} for "
        f'pairs whose kind says "object", < {fmt(scene["rotation_deg"])}° and < {fmt(scene["translation"])} for the '
        "others (scenes); translations in the clouds' units (metres here). Voxel: 4x the source's median point "
        "spacing, the same for every method.",
    ]
    return lines


def _summary_table(result: dict[str, Any]) -> str:
    rows = []
    for m, s in result["summary"].items():
        right = f"{s['right']}/{s['n']}"
        ratio = s["ms_ratio_fastest_peer"]
        rows.append(
            [
                LABELS.get(m, m),
                right,
                s["rot_median_object"],
                s["trans_median_object"],
                s["ms_median"],
                ratio,
                "-" if s["converged"] is None else f"{s['converged']}/{s['rated']}",
                s["suspect_precision"],
                s["suspect_recall"],
                str(s["errors"]),
            ]
        )
    fastest = next(iter(result["summary"].values()))["fastest_peer"]
    head = [
        "method",
        "right",
        "rot° (objects, median)",
        "trans (objects, median)",
        "median ms",
        f"÷ fastest peer ({fastest or '-'})",
        "converged",
        "suspect precision",
        "suspect recall",
        "errors",
    ]
    return md_table(head, rows)


def _pairs_table(result: dict[str, Any]) -> str:
    rows = [
        [
            p["id"],
            p["category"],
            f"{p['n_source']} / {p['n_target']}",
            p["voxel"],
            p["rotation_deg"] if p["rotation_deg"] is not None else math.nan,
            p["overlap"] if p["overlap"] is not None else math.nan,
        ]
        for p in result["pairs"]
    ]
    return md_table(["pair", "judged as", "points (source / target)", "voxel", "true rotation°", "overlap"], rows)


def _records_table(result: dict[str, Any]) -> str:
    pair_index = {p["id"]: i for i, p in enumerate(result["pairs"])}
    method_index = {m: i for i, m in enumerate(result["summary"])}
    rows = []
    for r in sorted(result["records"], key=lambda r: (pair_index[r["pair"]], method_index[r["method"]])):
        if r["error"] is not None:
            right = f"✗ ({r['error'][:60]})"
        else:
            right = "✓" if r["right"] else "✗"
        conf = r["confidence"]
        rows.append(
            [
                r["pair"],
                r["method"],
                r["rotation_deg"],
                r["translation"],
                r["ms"],
                right,
                r["status"] or "-",
                math.nan if conf is None else conf,
                r["candidate"] or "-",
            ]
        )
    return md_table(["pair", "method", "rot°", "trans", "ms", "right", "status", "confidence", "candidate"], rows)


def report(result: dict[str, Any]) -> str:
    """The markdown section: header, summary per method, the pairs, every record."""
    parts = [SECTION, "", *_header(result), "", _summary_table(result)]
    parts += ["", "### The pairs", "", _pairs_table(result)]
    parts += ["", "### Every pair and method", "", _records_table(result)]
    return "\n".join(parts)


def write_doc_section(path: Path, command: str, text: str) -> None:
    """Replace the ``## Real scans`` section of ``path`` (up to the next ``## `` heading) with ``text``, or
    append it; ``text`` starts with that heading and names ``command``."""
    assert text.startswith(SECTION) and command in text
    doc = path.read_text() if path.exists() else ""
    start = doc.find(f"\n{SECTION}\n")
    if start < 0:
        new = doc.rstrip("\n") + "\n\n" + text + "\n"
    else:
        end = doc.find("\n## ", start + 1)
        rest = doc[end:] if end >= 0 else "\n"
        new = doc[: start + 1] + text + "\n" + rest
    path.write_text(new)
