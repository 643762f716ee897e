"""Exit checks from trajectory prefixes: ICP + confidence after k agent steps; stop at the first confident one.

    python scripts/exit_check_probe.py noisy 200 [MODEL_DIR]

Runs the paper's 60-step agent once per pair (first N unseen test pairs, seed 1234), then ICP from the
estimate after 10..60 steps; prints the success of each fixed budget and of check schedules x thresholds.
(The numbers in docs/DESIGN.md "Exit checks and rescue" came from this script with the one-pass ICP.)
"""

import sys
import time

import numpy as np

from pranet.core.confidence import ConfidenceEstimator
from pranet.core.pipeline import register
from pranet.model.runtime import RewardModel
from pranet.service.icp import make_icp
from pranet.training.data import data_dir, load_modelnet40, test_indices
from pranet.training.evaluate import evaluate_pair
from pranet.training.samples import SETTINGS, make_pair, pair_rng


def main():
    setting, n = sys.argv[1], int(sys.argv[2])
    model = sys.argv[3] if len(sys.argv) > 3 else None
    ds = load_modelnet40(data_dir(), "test")
    idx = test_indices(ds.labels)
    shapes = ds.points[idx]
    scorer = RewardModel.load(model, threads=1) if model else RewardModel.load(threads=1)
    icp = make_icp()
    cps = [10, 15, 20, 25, 30, 40, 50, 60]
    S = np.zeros((n, len(cps)), bool)
    C = np.zeros((n, len(cps)))
    icp_t = []
    conf_t = []
    for i in range(n):
        pair = make_pair(shapes[i], setting, pair_rng(1234, setting, i), 60.0, 0.5, "isotropic")
        rng = np.random.default_rng([1234, SETTINGS.index(setting), i, 1])
        reg = register(pair.source, pair.target, scorer, rng, icp=None)
        norm = reg.normalization
        su, tu = norm.to_unit(pair.source), norm.to_unit(pair.target)
        t0 = time.perf_counter()
        est = ConfidenceEstimator(tu)
        conf_t.append(time.perf_counter() - t0)
        steps = reg.agent.steps
        for j, c in enumerate(cps):
            t0 = time.perf_counter()
            r = icp(su, tu, steps[min(c, len(steps)) - 1].transform)
            t1 = time.perf_counter()
            C[i, j] = est.evaluate(su, r.transform).score
            t2 = time.perf_counter()
            icp_t.append(t1 - t0)
            conf_t.append(t2 - t1)
            S[i, j] = evaluate_pair(
                pair.source, pair.target, pair.clean_source, norm.transform_to_world(r.transform), pair.T_gt
            ).success
    print(
        f"{setting} n={n}; ICP {np.median(icp_t) * 1e3:.2f} ms, confidence {np.median(conf_t) * 1e3:.2f} ms (medians)"
    )
    print("fixed:", {c: round(S[:, j].mean(), 3) for j, c in enumerate(cps)})
    for sched in ([20, 40, 60], [20, 30, 40, 50, 60], [15, 25, 40, 60], [10, 20, 30, 40, 60], [20, 60]):
        js = [cps.index(c) for c in sched]
        for th in (0.55, 0.7, 0.8, 0.9):
            succ = []
            used = []
            checks = []
            for i in range(n):
                for k, j in enumerate(js):
                    if C[i, j] >= th or k == len(js) - 1:
                        succ.append(S[i, j])
                        used.append(cps[j])
                        checks.append(k + 1)
                        break
            print(
                f"checkpoints {sched} th {th}: success {np.mean(succ):.3f}, "
                f"steps median {np.median(used):.0f} mean {np.mean(used):.1f}, "
                f"ICP runs mean {np.mean(checks):.2f}"
            )


if __name__ == "__main__":
    main()
