"""How many network calls the agent needs: the paper's call per step against the closed-form walk.

On ``--pairs`` validation pairs per setting (seen categories, held out from training), for each ``--walk`` value
(0 = the paper's protocol; k = up to k steps toward one estimate): the agent alone (PRANet-v1: mean and median
rotation error), PRANet-v2 (+ the service's ICP) and the service's default, with the network calls (rows of
``score.onnx``) and the median milliseconds of each. Backs docs/DESIGN.md, "The walk".

    python experiments/walk_probe.py --walk 0,3,5,10,60 --pairs 60
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def run(engine, config, pair, rng):
    """One registration: its result, milliseconds and score.onnx rows."""
    made = []  # every score function of the registration (the rescue makes its own)
    original = engine.scorer.batch_score_fn

    def counting(target):
        fn = original(target)
        made.append(fn.calls)
        return fn

    engine.scorer.batch_score_fn = counting
    try:
        t0 = time.perf_counter()
        reg = engine.register(pair.source, pair.target, config, rng)
        ms = (time.perf_counter() - t0) * 1e3
    finally:
        engine.scorer.batch_score_fn = original
    return reg, ms, sum(c["full"] for c in made)


def probe(engine, shapes, setting: str, pairs: int, walk: int) -> dict[str, float]:
    from pranet.core.metrics import isotropic_errors
    from pranet.core.registration_config import PAPER_V2, SERVICE_DEFAULT
    from pranet.training.samples import make_pair, pair_rng

    rows = []
    for i in range(pairs):
        rng = pair_rng(99, setting, i)
        pair = make_pair(shapes[i % len(shapes)], setting, rng)
        reg, ms, calls = run(engine, PAPER_V2.with_(walk_steps=walk), pair, rng)
        r1, _ = isotropic_errors(reg.agent_T_target_source, pair.T_gt)
        r2, t2 = isotropic_errors(reg.T_target_source, pair.T_gt)
        service, s_ms, s_calls = run(engine, SERVICE_DEFAULT.with_(walk_steps=walk), pair, pair_rng(99, setting, i))
        r3, t3 = isotropic_errors(service.T_target_source, pair.T_gt)
        rows.append((r1, r2, r2 < 1.0 and t2 < 0.01, ms, calls, r3 < 1.0 and t3 < 0.01, s_ms, s_calls))
    a = np.asarray(rows, dtype=np.float64)
    return {
        "v1_mean": a[:, 0].mean(),
        "v1_median": float(np.median(a[:, 0])),
        "v2_mean": a[:, 1].mean(),
        "v2_success": a[:, 2].mean(),
        "v2_ms": float(np.median(a[:, 3])),
        "v2_calls": float(np.median(a[:, 4])),
        "service_success": a[:, 5].mean(),
        "service_ms": float(np.median(a[:, 6])),
        "service_calls": float(np.median(a[:, 7])),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--walk", default="0,5,10,60", help="comma-separated walk_steps values")
    p.add_argument("--pairs", type=int, default=40)
    p.add_argument("--settings", default="clean,noisy,partial")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--data-dir", default=None)
    p.add_argument("--json", type=Path)
    args = p.parse_args()

    from pranet.engine.engine import Engine
    from pranet.training.data import data_dir, load_modelnet40, split_train_val

    data = load_modelnet40(data_dir(args.data_dir), "train")
    shapes = data.points[split_train_val(data.labels, 1234, 0.1).val]
    engine = Engine.load(threads=args.threads)
    out = []
    for setting in args.settings.split(","):
        for walk in (int(w) for w in args.walk.split(",")):
            row = {"setting": setting, "walk": walk, **probe(engine, shapes, setting, args.pairs, walk)}
            out.append(row)
            print(
                f"{setting:8s} walk {walk:3d}: v1 mean {row['v1_mean']:6.2f}° median {row['v1_median']:5.2f}°"
                f" | v2 mean {row['v2_mean']:6.2f}° ok {100 * row['v2_success']:5.1f} % {row['v2_ms']:5.0f} ms"
                f" {row['v2_calls']:4.0f} calls | service ok {100 * row['service_success']:5.1f} %"
                f" {row['service_ms']:5.0f} ms {row['service_calls']:4.0f} calls",
                flush=True,
            )
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
