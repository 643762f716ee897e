"""The agent and the service default with more points per cloud at inference than the model was trained on.

    python experiments/npoints_probe.py 40        # pairs per setting, validation shapes

Backs docs/DESIGN.md, "More points at inference (no retraining)".
"""

import sys
import time

import numpy as np

from pranet.core.metrics import isotropic_errors
from pranet.core.registration_config import PAPER_V1, SERVICE_DEFAULT
from pranet.engine.engine import Engine
from pranet.training.data import data_dir, load_modelnet40, split_train_val
from pranet.training.samples import make_pair, pair_rng

data = load_modelnet40(data_dir(None), "train")
shapes = data.points[split_train_val(data.labels, 1234, 0.1).val]
eng = Engine.load(threads=1)
for n in (256, 384, 512):
    eng.scorer.n_points = n
    for setting in ("partial", "noisy"):
        rows = []
        for i in range(int(sys.argv[1])):
            pair = make_pair(shapes[i % len(shapes)], setting, pair_rng(99, setting, i))
            reg = eng.register(pair.source, pair.target, PAPER_V1.with_(walk_steps=10), pair_rng(99, setting, i))
            r1 = isotropic_errors(reg.agent_T_target_source, pair.T_gt)[0]
            t0 = time.perf_counter()
            reg = eng.register(pair.source, pair.target, SERVICE_DEFAULT, pair_rng(99, setting, i))
            ms = 1e3 * (time.perf_counter() - t0)
            r, t = isotropic_errors(reg.T_target_source, pair.T_gt)
            rows.append((r1, r < 1 and t < 0.01, ms))
        a = np.array(rows, float)
        print(
            n,
            setting,
            "v1 mean",
            a[:, 0].mean().round(2),
            "median",
            np.median(a[:, 0]).round(2),
            "service",
            a[:, 1].mean().round(3),
            "ms",
            np.median(a[:, 2]).round(),
            flush=True,
        )
