"""The global match on sparse clouds (ModelNet40's 1024-point samples), on finer grids than the dense scans' one
voxel (4 spacings): per grid, how often its answer, refined by the pipeline's ICP, is a success by the benchmark's
thresholds, on pranet-bench's first N unseen-category pairs of a setting (its pairs and seeds). On a 1024-point
shape a 4-spacing grid leaves a few dozen cells, too few features to match.

    python experiments/sparse_global_probe.py --pairs 100 --setting partial --grids 1,0.5,0.35
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from pranet.core.metrics import SUCCESS_ROTATION_DEG, SUCCESS_TRANSLATION, isotropic_errors
from pranet.core.registration_config import DEFAULT_ICP_STAGES
from pranet.core.registration_context import prepare
from pranet.engine.global_match import kiss_matcher_match, ransac_global_match
from pranet.engine.icp import make_icp
from pranet.training.bench.records import as_float32, pair_seed
from pranet.training.data import data_dir, load_modelnet40, test_indices
from pranet.training.samples import make_pair, pair_rng


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=100)
    p.add_argument("--setting", default="partial")
    p.add_argument("--grids", default="1,0.5,0.35", help="the global match's voxel, in the data's voxels")
    args = p.parse_args()
    grids = [float(g) for g in args.grids.split(",")]
    icp = make_icp(DEFAULT_ICP_STAGES)
    data = load_modelnet40(data_dir(None), "test")
    shapes = test_indices(data.labels)[: args.pairs]
    ok = {(m, g): 0 for m in ("kiss", "ransac", "either") for g in grids}
    ms = {(m, g): [] for m in ("kiss", "ransac") for g in grids}
    for i, j in enumerate(shapes):
        pair = as_float32(make_pair(data.points[j], args.setting, pair_rng(0, args.setting, i), 60.0, 0.5))
        seed = pair_seed(0, args.setting, i)
        c = prepare(pair.source, pair.target, 256, np.random.default_rng(seed))
        for g in grids:
            coarse = replace(c.resolution, spacing=c.resolution.spacing * g)
            hit = False
            for name in ("kiss", "ransac"):
                t0 = time.perf_counter()
                if name == "kiss":
                    T = kiss_matcher_match(c.src_unit, c.tgt_unit, coarse, seed, c.viewpoint, 1.0)[0]
                else:
                    T = ransac_global_match(c.src_unit, c.tgt_unit, coarse, seed)
                ms[(name, g)].append(1e3 * (time.perf_counter() - t0))
                if T is None:
                    continue
                T = icp(c.src_unit, c.tgt_unit, T, c.resolution).transform
                rot, trans = isotropic_errors(c.norm.transform_to_world(T), pair.T_gt)
                good = rot < SUCCESS_ROTATION_DEG and trans < SUCCESS_TRANSLATION
                ok[(name, g)] += good
                hit |= good
            ok[("either", g)] += hit
    for g in grids:
        print(
            f"grid {g:g} voxel: KISS-Matcher {ok[('kiss', g)]}/{len(shapes)} ({np.median(ms[('kiss', g)]):.0f} ms), "
            f"RANSAC {ok[('ransac', g)]}/{len(shapes)} ({np.median(ms[('ransac', g)]):.0f} ms), "
            f"either {ok[('either', g)]}/{len(shapes)}"
        )


if __name__ == "__main__":
    main()
