"""How many source points the ICP stages need where the polish finishes: the service default with the stages'
``RANKING_SOURCE_POINTS`` at 2000 (as the RGB-D fragments keep) and at 1000 (shipped), per pair of each CSV: each
setting run twice, alternating, the faster kept; errors, status and milliseconds. Backs docs/DESIGN.md, "Fewer ICP
points where the polish finishes".

    python experiments/unseen_pairs.py /tmp/unseen
    python experiments/icp_points_probe.py ../shared/data/scans/pairs.csv /tmp/unseen/pairs.csv
"""

from __future__ import annotations

import sys
import time

import numpy as np

from pranet.client.io import read_point_cloud
from pranet.core.registration_config import SERVICE_DEFAULT
from pranet.engine import icp as icp_module
from pranet.engine.engine import Engine
from pranet.training.bench.scan_pairs import is_right, pose_errors, read_pairs, thresholds_for

SETTINGS = (2000, 1000)


def main() -> None:
    # One engine per setting: each ICP caches its target's preparation, the point count with it.
    engines = {n: Engine.load(threads=2) for n in SETTINGS}
    for n, engine in engines.items():
        icp_module.RANKING_SOURCE_POINTS = n
        engine.warm_up()
    for path in sys.argv[1:]:
        medians = {n: [] for n in SETTINGS}
        for pair in read_pairs(path):
            source, target = read_point_cloud(pair.source), read_point_cloud(pair.target)
            line = f"{pair.id:34s}"
            best = {n: float("inf") for n in SETTINGS}
            for n in SETTINGS * 2:
                icp_module.RANKING_SOURCE_POINTS = n
                t0 = time.perf_counter()
                reg = engines[n].register(source, target, SERVICE_DEFAULT)
                best[n] = min(best[n], (time.perf_counter() - t0) * 1e3)
            for n in SETTINGS:
                reg = engines[n].register(source, target, SERVICE_DEFAULT)
                rot, trans = pose_errors(reg.T_target_source, pair.T_gt)
                right = is_right(rot, trans, thresholds_for(pair.kind))
                line += (
                    f" | {n}: {best[n]:5.0f} ms {rot:.3f}° {trans:.3g} {'right' if right else 'wrong'} "
                    f"{reg.confidence.status}"
                )
                medians[n].append(best[n])
            print(line, flush=True)
        print(f"{path}: median ms " + ", ".join(f"{n}: {np.median(medians[n]):.0f}" for n in SETTINGS))


if __name__ == "__main__":
    main()
