"""Global mode against RANSAC+ICP and FGR+ICP on arbitrary rotations: ``python scripts/global_eval.py --pairs 50``.

Pairs: the first ``--pairs`` unseen-category ModelNet40 test shapes, ``make_pair(shape, setting,
pair_rng(seed, setting, i), max_angle_deg=180)`` (isotropic rotations up to 180°, translations up to
0.5), the same pairs for every method, all in one run (``training.evaluate.evaluate``). Methods:

- ``pranet-global``: ``Engine.register`` with ``PAPER_V2`` and ``init="global"``: the agent from ``--starts`` start
  rotations (one batched model call per step), the ``--refine-top`` most confident refined by ICP;
- ``service-global``: the service's default request with ``"init": "global"`` (``SERVICE_DEFAULT``: the walk, exit
  checks, the global match and the rescues, on the service's points per cloud), from the same starts;
- ``starts-icp``: PRANet-global without the agent (0 steps): ICP from the most confident starts, to show
  what the agent adds;
- ``pranet-v2``: the paper's PRANet-v2 from the identity (trained for rotations up to 60°);
- ``pranet-adaptive``: the service's default request from the identity (its global match reaches any rotation);
- ``ransac``, ``fgr``: RANSAC / FGR on FPFH features, refined by ICP (``training.baselines``).

Printed per method: success (RPMNet's: rotation < 1° and translation < 0.01), the share within 5°,
median and mean rotation error, median wall time (ms), and for PRANet the share flagged 'suspect'.

    python scripts/global_eval.py --pairs 50 --json runs/eval/global.json
    python scripts/global_eval.py --model runs/cpu/model --pairs 100 --setting clean --starts 24
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

ALL = ("pranet-global", "service-global", "starts-icp", "pranet-v2", "pranet-adaptive", "ransac", "fgr")


def global_runner(
    engine: Any, name: str, n_starts: int, refine_top: int, schedule: tuple[int, ...] | None, service: bool = False
) -> Any:
    """A ``training.evaluate.Runner`` for ``"init": "global"``: PRANet-v2 from ``n_starts`` starts, or with
    ``service`` the service's default request with ``"init": "global"`` (its walk, exit checks and rescues on its
    own points per cloud)."""
    from pranet.core.registration_config import PAPER_V2, SERVICE_DEFAULT
    from pranet.training.evaluate import MethodOutput, Runner

    if service:
        config = SERVICE_DEFAULT.with_(init="global", n_starts=n_starts, refine_top=refine_top)
    else:
        # The model's own N, not the paper's 1024: a batch of n_starts sources each step, each call about 11x the
        # cost at 1024 points.
        config = PAPER_V2.with_(
            init="global", n_starts=n_starts, refine_top=refine_top, schedule=schedule, agent_points=None
        )

    def run(pair: Any, rng: np.random.Generator) -> dict[str, MethodOutput]:
        reg = engine.register(pair.source, pair.target, config, rng)
        extra = {
            "timing_ms": reg.timing_ms,
            "confidence": reg.confidence.score,
            "status": reg.confidence.status,
            "start_index": reg.start_index,
        }
        return {name: MethodOutput(reg.T_target_source, reg.timing_ms["total"], extra=extra)}

    return Runner((name,), run)


def summary_row(name: str, records: list[dict[str, Any]]) -> dict[str, Any]:
    rot = np.array([r["rotation_deg"] for r in records], dtype=np.float64)
    ms = np.array([r["ms"] for r in records], dtype=np.float64)
    status = [r.get("status") for r in records]
    return {
        "method": name,
        "n": len(records),
        "success_rate": float(np.mean([r["success"] for r in records])),
        "within_5deg": float(np.mean(rot < 5.0)),
        "rotation_deg_median": float(np.median(rot)),
        "rotation_deg_mean": float(np.mean(rot)),
        "ms_median": float(np.nanmedian(ms)) if np.isfinite(ms).any() else float("nan"),
        "suspect_rate": float(np.mean([s == "suspect" for s in status])) if status and status[0] else None,
        "errors": sum(1 for r in records if r.get("error")),
    }


def format_table(rows: list[dict[str, Any]]) -> str:
    head = f"{'method':<14} {'success %':>9} {'<5° %':>7} {'rot med':>8} {'rot mean':>9} {'med ms':>8} {'suspect %':>9}"
    lines = [head, "-" * len(head)]
    for r in rows:
        suspect = f"{100 * r['suspect_rate']:.1f}" if r["suspect_rate"] is not None else "-"
        lines.append(
            f"{r['method']:<14} {100 * r['success_rate']:>9.1f} {100 * r['within_5deg']:>7.1f} "
            f"{r['rotation_deg_median']:>8.2f} {r['rotation_deg_mean']:>9.2f} {r['ms_median']:>8.0f} {suspect:>9}"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--pairs", type=int, default=50, help="pairs (the first unseen-category test shapes)")
    p.add_argument("--setting", choices=("clean", "noisy", "partial"), default="noisy")
    p.add_argument("--max-angle", type=float, default=180.0, help="max initial rotation (degrees, isotropic)")
    p.add_argument("--methods", default=",".join(ALL), help=f"comma-separated subset of {','.join(ALL)}")
    p.add_argument("--starts", type=int, default=24, help="start rotations of the global mode")
    p.add_argument("--refine-top", type=int, default=3, help="global mode: the most confident starts refined by ICP")
    p.add_argument("--model", default=None, help="model directory (default: the shipped model)")
    p.add_argument("--seed", type=int, default=1234)
    p.add_argument("--threads", type=int, default=1, help="onnxruntime threads and OMP_NUM_THREADS")
    p.add_argument("--data-dir", default=None, help="data root (default: $PRANET_DATA_DIR, else ../shared/data)")
    p.add_argument("--json", type=Path, default=None, help="write the summary and the per-pair records here")
    args = p.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    if unknown := sorted(set(methods) - set(ALL)):
        p.error(f"--methods: unknown {unknown}; choose from {','.join(ALL)}")
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))

    from pranet.engine.engine import Engine
    from pranet.training import baselines
    from pranet.training.data import data_dir, load_modelnet40, test_indices
    from pranet.training.evaluate import baseline_runner, evaluate, pranet_runner
    from pranet.training.reporting import nan_to_none

    data = load_modelnet40(data_dir(args.data_dir), "test")
    idx = test_indices(data.labels)[: args.pairs]
    engine = Engine.load(args.model, threads=args.threads)
    model = engine.scorer
    n_scales = len(model.schedule)
    runners = []
    if "pranet-global" in methods:
        runners.append(global_runner(engine, "pranet-global", args.starts, args.refine_top, None))
    if "service-global" in methods:
        runners.append(global_runner(engine, "service-global", args.starts, args.refine_top, None, service=True))
    if "starts-icp" in methods:
        runners.append(global_runner(engine, "starts-icp", args.starts, args.refine_top, (0,) * n_scales))
    if "pranet-v2" in methods:
        runners.append(pranet_runner(engine, ("pranet-v2",)))
    if "pranet-adaptive" in methods:
        runners.append(pranet_runner(engine, ("pranet-adaptive",)))
    if "ransac" in methods:
        runners.append(baseline_runner("ransac", baselines.ransac_icp))
    if "fgr" in methods:
        runners.append(baseline_runner("fgr", baselines.fgr_icp))

    t0 = time.perf_counter()
    result = evaluate(data.points[idx], args.setting, runners, seed=args.seed, max_angle_deg=args.max_angle)
    wall = time.perf_counter() - t0
    rows = [summary_row(m, result["records"][m]) for m in methods if m in result["records"]]
    info = model.info()
    print(
        f"\nglobal registration: {len(idx)} {args.setting} pairs, isotropic rotations <= {args.max_angle:g}°, "
        f"translations <= 0.5, seed {args.seed}; model {info['name']} {info['version']}; starts {args.starts}, "
        f"ICP on the best {args.refine_top}; {wall:.0f} s\n(success: rotation < 1° and translation < 0.01; "
        "ms: wall time per pair on this machine)"
    )
    print(format_table(rows))
    if args.json is not None:
        doc = {
            "config": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
            "model": info,
            "summary": rows,
            "records": result["records"],
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(nan_to_none(doc), indent=1))
        print(f"wrote {args.json}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
