"""PRANet-v1 and v2 (the paper's protocol: a network call per step, 20 + 40 steps) with the agent seeing a given
number of points per cloud (each point once, all of a smaller cloud), for one or more model directories, on the
validation shapes.

    python experiments/agent_points_probe.py model/default /tmp/m5 --points 256,1024 --pairs 150 --json out.json

Each (model, points) row prints mean / median rotation error of v1 and v2 per setting; ``--json`` keeps every
pair's errors (the same pairs for every row) for paired differences. Backs docs/DESIGN.md, "Every point for the
paper's agent".
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from pranet.core.metrics import isotropic_errors
from pranet.core.registration_config import PAPER_V2
from pranet.engine.engine import Engine
from pranet.training.data import data_dir, load_modelnet40, split_train_val
from pranet.training.samples import make_pair, pair_rng


def run(engine: Engine, shapes: np.ndarray, setting: str, n: int, pairs: int, offset: int) -> dict[str, list[float]]:
    v1, v2, ms = [], [], []
    config = PAPER_V2.with_(agent_points=n)
    for i in range(offset, offset + pairs):
        pair = make_pair(shapes[i % len(shapes)], setting, pair_rng(99, setting, i))
        t0 = time.perf_counter()
        reg = engine.register(pair.source, pair.target, config, pair_rng(99, setting, i))
        ms.append(1e3 * (time.perf_counter() - t0))
        v1.append(float(isotropic_errors(reg.agent_T_target_source, pair.T_gt)[0]))
        v2.append(float(isotropic_errors(reg.T_target_source, pair.T_gt)[0]))
    return {"v1": v1, "v2": v2, "ms": ms}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("models", nargs="+", type=Path)
    p.add_argument("--points", default="256,512")
    p.add_argument("--pairs", type=int, default=60)
    p.add_argument("--offset", type=int, default=0, help="first pair index (disjoint pair sets for a second look)")
    p.add_argument("--settings", default="clean,noisy,partial")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", type=Path)
    args = p.parse_args()

    data = load_modelnet40(data_dir(None), "train")
    shapes = data.points[split_train_val(data.labels, 1234, 0.1).val]
    rows = []
    for model in args.models:
        engine = Engine.load(model, threads=args.threads)
        for n in (int(x) for x in args.points.split(",")):
            for setting in args.settings.split(","):
                r = run(engine, shapes, setting, n, args.pairs, args.offset)
                rows.append({"model": str(model), "points": n, "setting": setting, **r})
                print(
                    f"{str(model):24s} {n:5d} {setting:8s} v1 {np.mean(r['v1']):6.2f} / {np.median(r['v1']):5.2f}°"
                    f"  >20° {np.mean(np.array(r['v1']) > 20):5.1%}"
                    f"  v2 {np.mean(r['v2']):6.2f} / {np.median(r['v2']):5.2f}°"
                    f"  {np.median(r['ms']):6.0f} ms",
                    flush=True,
                )
                if args.json:
                    args.json.write_text(json.dumps(rows))


if __name__ == "__main__":
    main()
