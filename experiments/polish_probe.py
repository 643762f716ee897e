"""How precisely each refinement finishes on the real-scan object pairs: from the truth turned 3° and moved 2 mm
(three starts per pair), Open3D's stages (2000 and 8000 source points), those followed by small_gicp's GICP, and
GICP alone (at 1 then ½ voxel, as the KISS-Matcher + small_gicp peer). Backs docs/DESIGN.md, "The polish".

    python experiments/polish_probe.py
"""

import time

import numpy as np
from scipy.spatial.transform import Rotation

import pranet.engine.icp as icpmod
from pranet.client.io import read_point_cloud
from pranet.core.registration_config import DEFAULT_ICP_STAGES
from pranet.core.registration_context import prepare
from pranet.training.bench.scan_pairs import pose_errors, read_pairs
from pranet.training.bench.scan_peers import gicp
from pranet.training.data import data_dir

root = data_dir(None) / "scans"
pairs = [p for p in read_pairs(root / "pairs.csv") if p.category == "object"]
rng = np.random.default_rng(0)
variants = {}
variants["current"] = icpmod.make_icp(DEFAULT_ICP_STAGES)
res = {k: [] for k in ["current", "src8000", "cur+gicp", "gicp_only"]}
for p in pairs:
    src = read_point_cloud(p.source)
    tgt = read_point_cloud(p.target)
    c = prepare(src, tgt, 256, np.random.default_rng(0))
    norm = c.norm
    for _trial in range(3):
        ax = rng.normal(size=3)
        ax /= np.linalg.norm(ax)
        D = np.eye(4)
        D[:3, :3] = Rotation.from_rotvec(ax * np.radians(3)).as_matrix()
        D[:3, 3] = rng.normal(size=3) * 0.002
        T0w = D @ p.T_gt
        T0 = norm.transform_to_unit(T0w)
        for name in res:
            t0 = time.perf_counter()
            if name == "current":
                icpmod.MAX_SOURCE_POINTS = 2000
                T = norm.transform_to_world(variants["current"](c.src_unit, c.tgt_unit, T0, c.resolution).transform)
            elif name == "src8000":
                icpmod.MAX_SOURCE_POINTS = 8000
                T = norm.transform_to_world(variants["current"](c.src_unit, c.tgt_unit, T0, c.resolution).transform)
                icpmod.MAX_SOURCE_POINTS = 2000
            elif name == "cur+gicp":
                T = norm.transform_to_world(variants["current"](c.src_unit, c.tgt_unit, T0, c.resolution).transform)
                v = c.resolution.voxel / norm.scale
                T = gicp(src, tgt, T, v, 1)
            else:
                v = c.resolution.voxel / norm.scale
                T = gicp(src, tgt, T0w, v, 1)
            ms = (time.perf_counter() - t0) * 1e3
            r, t = pose_errors(T, p.T_gt)
            res[name].append((r, t * 1000, ms))
    print(p.id, {k: tuple(np.round(np.median(np.array(v[-3:]), axis=0), 3)) for k, v in res.items()}, flush=True)
for k, v in res.items():
    a = np.array(v)
    print(
        k,
        "median rot",
        np.median(a[:, 0]).round(3),
        "trans mm",
        np.median(a[:, 1]).round(3),
        "ms",
        np.median(a[:, 2]).round(1),
    )
