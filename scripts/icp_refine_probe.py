import json
import sys

import numpy as np

from pranet.core.preprocess import fit_normalization
from pranet.service.icp import make_icp
from pranet.training.data import data_dir, load_modelnet40, test_indices
from pranet.training.evaluate import evaluate_pair
from pranet.training.samples import make_pair, pair_rng


def main():
    with open(sys.argv[1]) as fh:
        recs = json.load(fh)["records"][sys.argv[2]]
    setting = sys.argv[3]
    ds = load_modelnet40(data_dir(), "test")
    idx = test_indices(ds.labels)
    shapes = ds.points[idx]
    variants = {d: make_icp(max_distance=d) for d in (0.05, 0.03, 0.02)}
    p2l = make_icp(max_distance=0.05, method="point_to_plane")
    res = {k: [] for k in ["base", *variants, "p2l"]}
    for r in recs:
        i = r["pair"]
        pair = make_pair(shapes[i], setting, pair_rng(1234, setting, i), 60.0, 0.5, "isotropic")
        norm = fit_normalization(pair.source, pair.target)
        su, tu = norm.to_unit(pair.source), norm.to_unit(pair.target)
        T0 = norm.transform_to_unit(np.array(r["T_est"]))
        res["base"].append(r["success"])
        for d, f in [*variants.items(), ("p2l", p2l)]:
            T = norm.transform_to_world(f(su, tu, T0).transform)
            res[d].append(evaluate_pair(pair.source, pair.target, pair.clean_source, T, pair.T_gt).success)
    print({k: round(float(np.mean(v)), 4) for k, v in res.items()})


if __name__ == "__main__":
    main()
