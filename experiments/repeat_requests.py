"""The same request several times in one process, per real-scan pair: whether the answer changes (right or wrong,
status) and by how much (rotation, and translation in voxels, against the first run). Backs docs/DESIGN.md, "Same
request, same answer: not quite, on RGB-D fragments" (KISS-Matcher's matching runs on TBB threads; pin the process
to one CPU, ``taskset -c 0``, and every answer repeats exactly).

    python experiments/repeat_requests.py ../shared/data/scans/pairs.csv /tmp/unseen/pairs.csv --runs 3
"""

from __future__ import annotations

import argparse

from pranet.client.io import read_point_cloud
from pranet.engine.engine import Engine
from pranet.training.bench.scan_pairs import is_right, pose_errors, read_pairs, thresholds_for


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("pairs_csv", nargs="+")
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    engine = Engine.load(threads=args.threads)
    engine.warm_up()
    for csv_path in args.pairs_csv:
        for pair in read_pairs(csv_path):
            source, target = read_point_cloud(pair.source), read_point_cloud(pair.target)
            runs = [engine.register(source, target) for _ in range(args.runs)]
            right = [is_right(*pose_errors(r.T_target_source, pair.T_gt), thresholds_for(pair.kind)) for r in runs]
            moved = [pose_errors(r.T_target_source, runs[0].T_target_source) for r in runs[1:]]
            voxel = runs[0].resolution.voxel
            statuses = {r.confidence.status for r in runs}
            flip = "  CHANGED" if len(set(right)) > 1 or len(statuses) > 1 else ""
            print(
                f"{pair.id[:36]:36s} right {right} status {sorted(statuses)} spread "
                f"{max(m[0] for m in moved):.3f}° {max(m[1] for m in moved) / voxel:.2f} voxels{flip}",
                flush=True,
            )


if __name__ == "__main__":
    main()
