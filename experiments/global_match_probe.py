"""KISS-Matcher as the global candidate, per real-scan pair: about which origin its normals are turned (the unit
frame's centre or the input frame's origin, the pipeline's ``viewpoint``) and on which grid (in voxels). For each
choice: the matches its answer rests on, its milliseconds, and the answer after the pipeline's ICP stages (right by
the benchmark's thresholds, confidence). Backs docs/DESIGN.md, "The global match: where it looks from, on which
grid, and when RANSAC follows".

    python experiments/global_match_probe.py ../shared/data/scans/pairs.csv --grids 1,2,3
    python experiments/global_match_probe.py /tmp/unseen/pairs.csv --viewpoints centred,input --grids 1
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from pranet.client.io import read_point_cloud
from pranet.core.confidence import ConfidenceEstimator
from pranet.core.registration_config import DEFAULT_ICP_STAGES
from pranet.core.registration_context import prepare
from pranet.engine.global_match import kiss_matcher_match
from pranet.engine.icp import make_icp
from pranet.training.bench.scan_pairs import is_right, pose_errors, read_pairs, thresholds_for


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("pairs", type=Path, help="a pairs CSV (pranet-bench scans format)")
    p.add_argument("--grids", default="1,2", help="KISS-Matcher grids, in voxels")
    p.add_argument("--viewpoints", default="input", help="centred and/or input")
    args = p.parse_args()
    grids = [float(g) for g in args.grids.split(",")]
    views = args.viewpoints.split(",")
    icp = make_icp(DEFAULT_ICP_STAGES)
    totals: dict[str, list] = {f"{v}@{g:g}": [0, 0, []] for v in views for g in grids}
    for pair in read_pairs(args.pairs):
        clouds = prepare(read_point_cloud(pair.source), read_point_cloud(pair.target), 256, np.random.default_rng(0))
        estimator = ConfidenceEstimator(clouds.src_index, clouds.tgt_index, clouds.resolution)
        cells = []
        for view in views:
            viewpoint = clouds.viewpoint if view == "input" else None
            for grid in grids:
                key, total = f"{view}@{grid:g}", totals[f"{view}@{grid:g}"]
                t0 = time.perf_counter()
                T, inliers = kiss_matcher_match(clouds.src_unit, clouds.tgt_unit, clouds.resolution, 0, viewpoint, grid)
                ms = 1e3 * (time.perf_counter() - t0)
                total[2].append(ms)
                if T is None:
                    cells.append(f"{key}: none {ms:4.0f} ms")
                    continue
                refined = icp(clouds.src_unit, clouds.tgt_unit, T, clouds.resolution).transform
                right = is_right(
                    *pose_errors(clouds.norm.transform_to_world(refined), pair.T_gt), thresholds_for(pair.kind)
                )
                score = estimator.evaluate(refined).score
                total[0] += right
                total[1] += right and score >= estimator.threshold
                cells.append(f"{key}: {'R' if right else 'w'} {score:.2f} ({inliers:3d} matches) {ms:4.0f} ms")
        print(f"{pair.id[:30]:30s} | " + " | ".join(cells), flush=True)
    for key, (right, converged, ms) in totals.items():
        print(f"{key}: right {right}, right and converged {converged}, median {np.median(ms):.0f} ms")


if __name__ == "__main__":
    main()
