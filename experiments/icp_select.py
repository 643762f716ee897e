"""Choose the ICP refinement of PRANet-v2 and the service: candidate stage lists, each run inside the service's
default pipeline (exit checks 20/40, rescues), on the same pairs (docs/DESIGN.md, "ICP of PRANet-v2").

    python experiments/icp_select.py                  # validation shapes, 511 noisy + 200 partial pairs (~20 min)
    python experiments/icp_select.py --split test --pairs 0,300   # the unseen test shapes (1266 + 300), afterwards

``--split val``: the shapes of the seen categories that training held out for validation
(``training.data.split_train_val`` with the committed split seed), never trained on; pairs seeded 4321.
Pairs and per-pair seeds are built as pranet-bench builds them (float32 clouds, ``bench.pair_seed``).
``--split test``: the unseen-category test shapes, as pranet-eval and pranet-bench build them (seed 1234).
Prints one markdown table: per setting and candidate, the success rate (rotation < 1° and translation < 0.01)
and the median latency.
"""

from __future__ import annotations

import argparse

import numpy as np

from pranet.core.metrics import SUCCESS_ROTATION_DEG, SUCCESS_TRANSLATION, isotropic_errors
from pranet.core.registration_config import POINT_TO_PLANE, POINT_TO_POINT, SERVICE_DEFAULT, two_windows
from pranet.engine.engine import Engine
from pranet.training.bench import as_float32, pair_seed, pranet_method
from pranet.training.config import PRESETS
from pranet.training.data import data_dir, load_modelnet40, split_train_val, test_indices
from pranet.training.samples import make_pair, pair_rng

CANDIDATES = {
    "point-to-point 0.1, 0.05 (1.1.0)": two_windows(POINT_TO_POINT),
    "point-to-plane 0.1 -> point-to-point 0.05": ((POINT_TO_PLANE, 0.1), (POINT_TO_POINT, 0.05)),
    "point-to-plane 0.1 -> point-to-point 0.1, 0.05": ((POINT_TO_PLANE, 0.1), *two_windows(POINT_TO_POINT)),
    "point-to-plane 0.1, 0.05 -> point-to-point 0.1, 0.05": two_windows(POINT_TO_PLANE) + two_windows(POINT_TO_POINT),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--split", choices=("val", "test"), default="val")
    ap.add_argument("--settings", default="noisy,partial")
    ap.add_argument("--pairs", default="0,200", help="pairs per setting, comma-separated (0: all of the split)")
    ap.add_argument("--model", default=None, help="model directory (default: the shipped one)")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    if args.split == "val":
        data = load_modelnet40(data_dir(), "train")
        idx, seed = split_train_val(data.labels, PRESETS["cpu"].split_seed).val, 4321
    else:
        data = load_modelnet40(data_dir(), "test")
        idx, seed = test_indices(data.labels), 1234
    engine = Engine.load(args.model, threads=args.threads)
    print(f"split {args.split}: {len(idx)} shapes, pair seed {seed}, model {engine.scorer.info()['version']}\n")
    print("| setting | ICP stages | pairs | success % | median ms |")
    print("| --- | --- | --- | --- | --- |")
    settings = args.settings.split(",")
    counts = [int(n) for n in args.pairs.split(",")]
    counts = (counts + counts[-1:] * len(settings))[: len(settings)]
    for setting, n in zip(settings, counts, strict=True):
        pairs = [
            as_float32(make_pair(data.points[j], setting, pair_rng(seed, setting, i), 60.0, 0.5))
            for i, j in enumerate(idx[: n or None])
        ]
        for name, stages in CANDIDATES.items():
            run = pranet_method(engine, SERVICE_DEFAULT.with_(icp_stages=stages))
            ok, ms = [], []
            for i, pair in enumerate(pairs):
                out = run(pair, pair_seed(seed, setting, i))  # the service's default: exit checks, both rescues
                ms.append(out.ms)
                rot, trans = isotropic_errors(out.transform, pair.T_gt)
                ok.append(rot < SUCCESS_ROTATION_DEG and trans < SUCCESS_TRANSLATION)
            print(f"| {setting} | {name} | {len(pairs)} | {100 * np.mean(ok):.1f} | {np.median(ms):.0f} |", flush=True)


if __name__ == "__main__":
    main()
