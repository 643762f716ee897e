"""What the first ICP stage tells about a candidate: per real-scan pair, the agent's estimate after its coarse phase
and the global match, each refined by the first (8-spacing) stage only and by all stages; the quick confidence
after the first stage, the final confidence, whether the result is right, and the milliseconds of each. Backs
docs/DESIGN.md, "The ICP gate".

    python experiments/icp_gate_probe.py
"""

import time

import numpy as np

from pranet.client.io import read_point_cloud
from pranet.core.confidence import ConfidenceEstimator
from pranet.core.registration_config import DEFAULT_ICP_STAGES, SERVICE_DEFAULT
from pranet.core.registration_context import prepare
from pranet.engine.engine import Engine
from pranet.engine.global_match import global_matches
from pranet.engine.icp import make_icp
from pranet.training.bench.scan_pairs import is_right, pose_errors, read_pairs, thresholds_for
from pranet.training.data import data_dir

root = data_dir(None) / "scans"
eng = Engine.load(threads=1)
full = make_icp(DEFAULT_ICP_STAGES)
first = make_icp(DEFAULT_ICP_STAGES[:1])
for p in read_pairs(root / "pairs.csv"):
    if "lidar" in p.id:
        continue
    src = read_point_cloud(p.source)
    tgt = read_point_cloud(p.target)
    c = prepare(src, tgt, 256, np.random.default_rng(0))
    norm = c.norm
    est = ConfidenceEstimator(c.src_index, c.tgt_index, c.resolution)
    reg = eng.register(
        src,
        tgt,
        SERVICE_DEFAULT.with_(
            global_match=False,
            rescue_window=None,
            rescue_restarts=False,
            exit_checks=(20,),
            polish=False,
            schedule=(20, 0),
        ),
        np.random.default_rng(0),
    )
    cands = {"agent": norm.transform_to_unit(reg.agent_T_target_source)}
    G = next(global_matches(c.src_unit, c.tgt_unit, c.resolution, 0, c.viewpoint), None)  # its first candidate
    if G is not None:
        cands["global"] = G
    for name, T0 in cands.items():
        t0 = time.perf_counter()
        T1 = first(c.src_unit, c.tgt_unit, T0, c.resolution).transform
        t1 = time.perf_counter()
        q1 = est.evaluate(T1, 256).score
        t2 = time.perf_counter()
        Tf = full(c.src_unit, c.tgt_unit, T0, c.resolution).transform
        t3 = time.perf_counter()
        r, t = pose_errors(norm.transform_to_world(Tf), p.T_gt)
        ok = is_right(r, t, thresholds_for(p.kind))
        print(
            f"{p.id[:26]:26s} {name:6s} right {ok!s:5s} stage1 {1e3 * (t1 - t0):5.0f} ms q1 {q1:.2f}"
            f" | full {1e3 * (t3 - t2):5.0f} ms conf {est.evaluate(Tf).score:.2f}",
            flush=True,
        )
