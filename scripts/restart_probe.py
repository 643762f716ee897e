"""Restarts around an estimate for the suspect results of a pranet-eval run (its pranet-adaptive records).

    pranet-eval --setting noisy --limit 300 --methods pranet-adaptive --json /tmp/ad.json
    python scripts/restart_probe.py /tmp/ad.json noisy 30 axes 20,0

ANGLE, then ``axes`` (6 starts: +-ANGLE about x, y, z) or a number K (K well-spread axes at ANGLE), then
the agent schedule of the restarts. Prints how many suspect results the restarts fix or break, and their
mean cost. (The numbers in docs/DESIGN.md were taken before the restarts became part of pranet-adaptive.)
"""

import json
import sys
import time

import numpy as np
from scipy.spatial.transform import Rotation

from pranet.core.agent import run_agent_batch
from pranet.core.confidence import ConfidenceEstimator
from pranet.core.preprocess import fit_normalization, resample
from pranet.core.se3 import make_transform
from pranet.model.runtime import RewardModel
from pranet.service.icp import make_icp
from pranet.training.data import data_dir, load_modelnet40, test_indices
from pranet.training.evaluate import evaluate_pair
from pranet.training.samples import make_pair, pair_rng


def main():
    recs = json.load(open(sys.argv[1]))["records"]["pranet-adaptive"]
    setting = sys.argv[2]
    angle = float(sys.argv[3])
    K = sys.argv[4]
    sched = tuple(int(x) for x in sys.argv[5].split(","))
    ds = load_modelnet40(data_dir(), "test")
    idx = test_indices(ds.labels)
    shapes = ds.points[idx]
    scorer = RewardModel.load(threads=1)
    icp = make_icp()
    if K == "axes":
        rots = [Rotation.from_rotvec(np.deg2rad(angle) * s * e).as_matrix() for e in np.eye(3) for s in (1, -1)]
    else:
        from pranet.core.starts import start_rotations

        rots = [Rotation.from_matrix(Q).as_rotvec() for Q in start_rotations(int(K))]
        rots = [Rotation.from_rotvec(v / max(np.linalg.norm(v), 1e-9) * np.deg2rad(angle)).as_matrix() for v in rots]
    fixed = 0
    broke = 0
    n = 0
    ts = []
    for r in recs:
        if r["status"] != "suspect":
            continue
        n += 1
        i = r["pair"]
        pair = make_pair(shapes[i], setting, pair_rng(1234, setting, i), 60.0, 0.5, "isotropic")
        t0 = time.perf_counter()
        norm = fit_normalization(pair.source, pair.target)
        su, tu = norm.to_unit(pair.source), norm.to_unit(pair.target)
        rng = np.random.default_rng(0)
        sn, tn = resample(su, 256, rng), resample(tu, 256, rng)
        T0 = norm.transform_to_unit(np.array(r["T_est"]))
        c = T0[:3, :3] @ sn.mean(0) + T0[:3, 3]
        starts = []
        for Q in rots:  # rotate the current estimate about the moved source centroid
            R = Q @ T0[:3, :3]
            starts.append(make_transform(R, c - R @ sn.mean(0)))
        res = run_agent_batch(sn, tn, scorer.batch_score_fn(tn), scorer.table, np.array(starts), sched)
        est = ConfidenceEstimator(tu)
        quick = ConfidenceEstimator(tu, max_target=1024)
        order = np.argsort([-quick.evaluate(su, a.transform, max_source=256).score for a in res])[:3]
        best = (r["confidence"], None)
        for b in order:
            out = icp(su, tu, res[b].transform)
            cf = est.evaluate(su, out.transform).score
            if cf > best[0]:
                best = (cf, out.transform)
        ts.append(time.perf_counter() - t0)
        if best[1] is not None:
            ok = evaluate_pair(
                pair.source, pair.target, pair.clean_source, norm.transform_to_world(best[1]), pair.T_gt
            ).success
            fixed += ok and not r["success"]
            broke += (not ok) and r["success"]
    print(
        f"{setting} angle {angle} starts {len(rots)} sched {sched}: "
        f"suspect {n}, fixed {fixed}, broke {broke}, mean {np.mean(ts) * 1e3:.0f} ms"
    )


if __name__ == "__main__":
    main()
