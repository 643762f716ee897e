"""The agent again on the overlap its first estimate sees: does a second pass on the cropped clouds fix a partial
pair? Per validation pair (agent_probe's shapes and seeds): PRANet-v1 (the paper's 60 steps), then each cloud cut
to its points within ``r`` of the other under that estimate, and the agent's 60 steps again from there; the agent's
errors (mean / median rotation, median translation) after each pass. No training, no ICP. Backs docs/DESIGN.md,
"The agent on its own overlap".

    python experiments/overlap_crop_probe.py --pairs 60 --radii 0.1,0.2 --passes 2
"""

from __future__ import annotations

import argparse

import numpy as np

from pranet.core.metrics import isotropic_errors
from pranet.core.nearest import PointIndex
from pranet.core.registration_config import PAPER_V1
from pranet.core.se3 import apply_transform
from pranet.engine.engine import Engine
from pranet.training.data import data_dir, load_modelnet40, split_train_val
from pranet.training.samples import make_pair, pair_rng

MIN_POINTS = 64  # a crop with fewer points keeps the whole cloud


def cropped(source: np.ndarray, target: np.ndarray, T: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The points of each cloud within ``radius`` of the other under ``T`` (target ≈ T · source)."""
    moved = apply_transform(T, source)
    keep_s = PointIndex(target).nearest(moved) < radius
    keep_t = PointIndex(moved).nearest(target) < radius
    if keep_s.sum() < MIN_POINTS or keep_t.sum() < MIN_POINTS:
        return source, target
    return source[keep_s], target[keep_t]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=60)
    p.add_argument("--setting", default="partial")
    p.add_argument("--radii", default="0.1,0.2", help="crop radii, unit-sphere units (inf: the whole clouds)")
    p.add_argument("--passes", type=int, default=2, help="passes after the first")
    p.add_argument("--later", default="20,40", help="the later passes' schedule (steps per scale; '0,40': fine only)")
    p.add_argument("--model", default=None)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    engine = Engine.load(args.model, threads=args.threads)
    data = load_modelnet40(data_dir(None), "train")
    shapes = data.points[split_train_val(data.labels, 1234, 0.1).val]
    radii = [float(r) for r in args.radii.split(",")]
    later = PAPER_V1.with_(schedule=tuple(int(n) for n in args.later.split(",")))
    errors = {("first", 0.0): []} | {(k, r): [] for r in radii for k in range(1, args.passes + 1)}
    for i in range(args.pairs):
        rng = pair_rng(99, args.setting, i)
        pair = make_pair(shapes[i % len(shapes)], args.setting, rng)
        first = engine.register(pair.source, pair.target, PAPER_V1, pair_rng(99, args.setting, i))
        T1 = first.agent_T_target_source
        errors[("first", 0.0)].append(isotropic_errors(T1, pair.T_gt))
        for r in radii:
            T = T1
            for k in range(1, args.passes + 1):
                src, tgt = cropped(pair.source, pair.target, T, r)
                again = engine.register(apply_transform(T, src), tgt, later, np.random.default_rng(i))
                T = again.agent_T_target_source @ T
                errors[(k, r)].append(isotropic_errors(T, pair.T_gt))
    print(
        f"{args.setting}, {args.pairs} validation pairs: the agent alone (PRANet-v1), rotation mean / median, "
        "translation median"
    )
    for (k, r), e in errors.items():
        a = np.array(e)
        name = "first pass" if k == "first" else f"cropped at {r:g}, pass {k}"
        print(f"  {name:28s} {a[:, 0].mean():6.2f}° {np.median(a[:, 0]):6.2f}°  {np.median(a[:, 1]):.4f}")


if __name__ == "__main__":
    main()
