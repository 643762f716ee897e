"""How well the ``status`` flag catches failed registrations: ``python scripts/confidence_eval.py --pairs 100``.

A failure is a result with a rotation error above ``--fail-deg`` (5°). The flag is ``status ==
"suspect"``, i.e. ``confidence < threshold``. On ModelNet40's unseen-category test shapes, noisy and
partial pairs (``training.samples.make_pair``, rotations up to 60°), PRANet-v1 (agent) and -v2
(agent + ICP) as ``pranet-eval`` runs them (``training.evaluate.pranet_runner``, which records the
confidence of each result):

- calibration split: the last ``--calibration`` test shapes, pairs from seed ``--seed + 1``; the
  threshold is chosen there (the best F1 of failure detection, or the best precision at a recall of at
  least ``--min-recall``);
- evaluation split: the first ``--pairs`` test shapes with ``pranet-eval``'s pairs (seed ``--seed``,
  default 1234); precision and recall of the flag there, with the calibrated threshold and with the one
  the service ships (``core.confidence.DEFAULT_THRESHOLD``); AUC (threshold-free).

The two splits share no shape. The printed threshold is what ``DEFAULT_THRESHOLD`` should become.

    python scripts/confidence_eval.py --pairs 100 --calibration 100 --json runs/eval/confidence.json
    python scripts/confidence_eval.py --model runs/cpu/model --pairs 300 --calibration 300
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

METHODS = ("pranet-v1", "pranet-v2")


def flag_stats(confidence: np.ndarray, failed: np.ndarray, threshold: float) -> dict[str, float]:
    """Precision/recall/F1 of ``confidence < threshold`` as a detector of ``failed`` (both ``(n,)``)."""
    flagged = confidence < threshold
    tp = int(np.sum(flagged & failed))
    precision = tp / flagged.sum() if flagged.any() else float("nan")
    recall = tp / failed.sum() if failed.any() else float("nan")
    f1 = 2 * precision * recall / (precision + recall) if tp else 0.0
    return {
        "threshold": float(threshold),
        "precision": float(precision),
        "recall": float(recall),
        "f1": float(f1),
        "flagged": int(flagged.sum()),
        "failures": int(failed.sum()),
        "n": len(failed),
    }


def choose_threshold(
    confidence: np.ndarray, failed: np.ndarray, criterion: str = "f1", min_recall: float = 0.9
) -> dict[str, float]:
    """The threshold (a midpoint between observed confidences) that maximises ``criterion`` on this split."""
    values = np.unique(confidence)
    candidates = np.concatenate([[values[0] - 1e-6], (values[1:] + values[:-1]) / 2, [values[-1] + 1e-6]])
    best: dict[str, float] | None = None
    for t in candidates:
        s = flag_stats(confidence, failed, t)
        if criterion == "f1":
            key = s["f1"]
        else:  # the best precision among thresholds that reach the recall
            key = s["precision"] if s["recall"] >= min_recall and np.isfinite(s["precision"]) else -1.0
        if best is None or key > best["_key"]:
            best = {**s, "_key": key}
    assert best is not None
    best.pop("_key")
    return best


def auc(confidence: np.ndarray, failed: np.ndarray) -> float:
    """P(a success scores higher than a failure): how well the confidence ranks, threshold-free."""
    good, bad = confidence[~failed], confidence[failed]
    if not len(good) or not len(bad):
        return float("nan")
    return float((good[:, None] > bad[None]).mean() + 0.5 * (good[:, None] == bad[None]).mean())


def collect(
    shapes: np.ndarray, settings: list[str], seed: int, runner: Any, max_angle: float
) -> dict[str, dict[str, np.ndarray]]:
    """``{method: {"confidence": (n,), "rotation_deg": (n,)}}`` over all ``settings``, in that order."""
    from pranet.training.evaluate import evaluate

    out: dict[str, dict[str, list[float]]] = {m: {"confidence": [], "rotation_deg": []} for m in METHODS}
    for setting in settings:
        result = evaluate(shapes, setting, [runner], seed=seed, max_angle_deg=max_angle, progress=True)
        for method, records in result["records"].items():
            for r in records:
                out[method]["confidence"].append(r.get("confidence", np.nan))
                out[method]["rotation_deg"].append(r["rotation_deg"])
    return {m: {k: np.asarray(v, dtype=np.float64) for k, v in d.items()} for m, d in out.items()}


def _row(name: str, s: dict[str, float]) -> str:
    return (
        f"  {name:<30} threshold {s['threshold']:.3f}  precision {100 * s['precision']:5.1f} %  "
        f"recall {100 * s['recall']:5.1f} %  F1 {s['f1']:.3f}  (flagged {s['flagged']}, failures {s['failures']} "
        f"of {s['n']})"
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--pairs", type=int, default=100, help="evaluation pairs per setting (first test shapes)")
    p.add_argument("--calibration", type=int, default=100, help="calibration pairs per setting (last test shapes)")
    p.add_argument("--settings", default="noisy,partial", help="comma-separated subset of clean,noisy,partial")
    p.add_argument("--fail-deg", type=float, default=5.0, help="a failure: rotation error above this (degrees)")
    p.add_argument("--criterion", choices=("f1", "recall"), default="f1", help="how the threshold is chosen")
    p.add_argument("--min-recall", type=float, default=0.9, help="with --criterion recall: the recall to reach")
    p.add_argument("--max-angle", type=float, default=60.0, help="max initial rotation of the pairs (degrees)")
    p.add_argument("--model", default=None, help="model directory (default: the shipped model)")
    p.add_argument("--seed", type=int, default=1234, help="seed of the evaluation pairs (pranet-eval's default)")
    p.add_argument("--threads", type=int, default=1, help="onnxruntime threads and OMP_NUM_THREADS")
    p.add_argument("--data-dir", default=None, help="data root (default: $PRANET_DATA_DIR, else ../shared/data)")
    p.add_argument("--json", type=Path, default=None, help="write the per-pair values and the results here")
    args = p.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))

    from pranet.core.confidence import DEFAULT_THRESHOLD
    from pranet.engine.engine import Engine
    from pranet.training.data import data_dir, load_modelnet40, test_indices
    from pranet.training.evaluate import pranet_runner
    from pranet.training.reporting import nan_to_none

    settings = [s.strip() for s in args.settings.split(",") if s.strip()]
    data = load_modelnet40(data_dir(args.data_dir), "test")
    idx = test_indices(data.labels)
    if args.pairs + args.calibration > len(idx):
        p.error(f"--pairs + --calibration must not exceed the {len(idx)} test shapes (the splits share none)")
    eval_idx, cal_idx = idx[: args.pairs], idx[len(idx) - args.calibration :]
    engine = Engine.load(args.model, threads=args.threads)
    runner = pranet_runner(engine, METHODS)
    t0 = time.perf_counter()
    print(f"calibration: {len(cal_idx)} shapes x {settings}, seed {args.seed + 1}", file=sys.stderr)
    cal = collect(data.points[cal_idx], settings, args.seed + 1, runner, args.max_angle)
    print(f"evaluation: {len(eval_idx)} shapes x {settings}, seed {args.seed}", file=sys.stderr)
    ev = collect(data.points[eval_idx], settings, args.seed, runner, args.max_angle)

    info = engine.scorer.info()
    print(
        f"\nconfidence as a failure detector (failure: rotation error > {args.fail_deg:g}°; flag: status 'suspect' "
        f"= confidence < threshold)\nmodel {info['name']} {info['version']}, settings {settings}, rotations <= "
        f"{args.max_angle:g}°, calibration {len(cal_idx)} + evaluation {len(eval_idx)} shapes per setting, "
        f"{time.perf_counter() - t0:.0f} s"
    )
    results: dict[str, Any] = {}
    for method in METHODS:
        c_conf, c_fail = cal[method]["confidence"], cal[method]["rotation_deg"] > args.fail_deg
        e_conf, e_fail = ev[method]["confidence"], ev[method]["rotation_deg"] > args.fail_deg
        chosen = choose_threshold(c_conf, c_fail, args.criterion, args.min_recall)
        on_eval = flag_stats(e_conf, e_fail, chosen["threshold"])
        shipped = flag_stats(e_conf, e_fail, DEFAULT_THRESHOLD)
        results[method] = {
            "calibration": chosen,
            "evaluation": on_eval,
            "evaluation_shipped_threshold": shipped,
            "auc_evaluation": auc(e_conf, e_fail),
            "failure_rate_evaluation": float(e_fail.mean()),
            "median_confidence_evaluation": {
                "success": float(np.median(e_conf[~e_fail])) if (~e_fail).any() else None,
                "failure": float(np.median(e_conf[e_fail])) if e_fail.any() else None,
            },
        }
        r = results[method]
        print(
            f"\n{method}: failures {100 * r['failure_rate_evaluation']:.1f} % of the evaluation pairs, AUC "
            f"{r['auc_evaluation']:.3f}, median confidence success {r['median_confidence_evaluation']['success']} / "
            f"failure {r['median_confidence_evaluation']['failure']}"
        )
        print(_row(f"calibration (chosen, {args.criterion})", chosen))
        print(_row("evaluation, chosen threshold", on_eval))
        print(_row("evaluation, shipped threshold", shipped))
    if args.json is not None:
        doc = {
            "config": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
            "model": info,
            "shipped_threshold": DEFAULT_THRESHOLD,
            "results": results,
            "calibration": {m: {k: v.tolist() for k, v in d.items()} for m, d in cal.items()},
            "evaluation": {m: {k: v.tolist() for k, v in d.items()} for m, d in ev.items()},
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(nan_to_none(doc), indent=1))
        print(f"wrote {args.json}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
