"""Compare reward-network candidates on the validation shapes (seen categories, held out from training).

For each checkpoint (exported to a temporary ONNX directory) or model directory: PRANet-v1 (the agent
alone, 60 steps), PRANet-v2 (+ the service's ICP stages) and the service's default (``SERVICE_DEFAULT``) on
``--pairs`` pairs per setting, through the engine as the service runs them. Backs docs/DESIGN.md, "The agent
(model 2.0.0)".

    python experiments/agent_probe.py runs/cpu/best.pt runs/probe-a/last.pt --pairs 40
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def load_engine(path: Path, tmp: Path, threads: int = 2):
    from pranet.engine.engine import Engine

    if path.is_dir():
        return Engine.load(path, threads=threads)
    from pranet.model.export import card_from_checkpoint, export_model, load_checkpoint

    net, ck = load_checkpoint(path)
    out = tmp / path.parent.name
    export_model(net, out, card_from_checkpoint(ck, "probe", "0.0.0"))
    return Engine.load(out, threads=threads)


def probe(engine, shapes: np.ndarray, setting: str, pairs: int) -> dict[str, float]:
    from pranet.core.metrics import isotropic_errors
    from pranet.core.registration_config import PAPER_V2, SERVICE_DEFAULT
    from pranet.training.samples import make_pair, pair_rng

    v1, v2, ok, ms, service_ok, service_ms = [], [], [], [], [], []
    for i in range(pairs):
        rng = pair_rng(99, setting, i)
        pair = make_pair(shapes[i % len(shapes)], setting, rng)
        t0 = time.perf_counter()
        reg = engine.register(pair.source, pair.target, PAPER_V2, rng)
        ms.append((time.perf_counter() - t0) * 1e3)
        r1, _ = isotropic_errors(reg.agent_T_target_source, pair.T_gt)
        r2, t2 = isotropic_errors(reg.T_target_source, pair.T_gt)
        v1.append(r1)
        v2.append(r2)
        ok.append(bool(r2 < 1.0 and t2 < 0.01))
        t0 = time.perf_counter()
        service = engine.register(pair.source, pair.target, SERVICE_DEFAULT, pair_rng(99, setting, i))
        service_ms.append((time.perf_counter() - t0) * 1e3)
        r3, t3 = isotropic_errors(service.T_target_source, pair.T_gt)
        service_ok.append(bool(r3 < 1.0 and t3 < 0.01))
    return {
        "v1_mean": float(np.mean(v1)),
        "v1_median": float(np.median(v1)),
        "v2_mean": float(np.mean(v2)),
        "v2_success": float(np.mean(ok)),
        "ms_median": float(np.median(ms)),
        "service_success": float(np.mean(service_ok)),
        "service_ms_median": float(np.median(service_ms)),
        # Per pair, in pair order, for paired differences between models (the same pairs for every model).
        "per_pair": {"v1": [float(e) for e in v1], "v2": [float(e) for e in v2], "service_ok": service_ok},
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("models", nargs="+", type=Path, help="checkpoints (.pt) or model directories")
    p.add_argument("--pairs", type=int, default=40)
    p.add_argument("--settings", default="clean,noisy,partial")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--json", type=Path)
    p.add_argument("--threads", type=int, default=2, help="onnxruntime threads (1 beside other work)")
    args = p.parse_args()

    from pranet.training.data import data_dir, load_modelnet40, split_train_val

    data = load_modelnet40(data_dir(args.data_dir), "train")
    shapes = data.points[split_train_val(data.labels, 1234, 0.1).val]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for path in args.models:
            engine = load_engine(path, Path(tmp), args.threads)
            for setting in args.settings.split(","):
                row = {"model": str(path), "setting": setting, **probe(engine, shapes, setting, args.pairs)}
                rows.append(row)
                print(
                    f"{str(path):40s} {setting:8s} v1 mean {row['v1_mean']:6.2f}° median {row['v1_median']:6.2f}°"
                    f"  v2 mean {row['v2_mean']:6.2f}° success {100 * row['v2_success']:5.1f} %"
                    f"  {row['ms_median']:6.0f} ms; service default {100 * row['service_success']:5.1f} %"
                    f" {row['service_ms_median']:6.0f} ms",
                    flush=True,
                )
                # After every row: a probe cut short (the session's end) keeps the settings it finished.
                if args.json:
                    args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
