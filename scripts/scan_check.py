"""Register the real scans in ``../shared/data/scans`` in-process and score them against their ground truth.

    python scripts/scan_check.py [--model DIR] [--threads 1]

Pairs: bunny bun045 -> bun000 and bun090 -> bun000 (``bun.conf``), the 3DMatch fragments (``3dmatch_gt.txt``).
Modes: PRANet-v2 as the paper (60 steps, ICP) and the service's default (exit checks, rescue). Prints one row
per pair and mode: errors, confidence, wall time and where it went.

Bunny ground truth as ``SOURCES.md`` describes: each ``bmesh`` line maps its scan into the common frame as
``p_world = R(q)ᵀ p + t``; ``T_target_source = inv(T_world_target) @ T_world_source``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial.transform import Rotation

from pranet.client.io import read_point_cloud
from pranet.core.metrics import isotropic_errors
from pranet.core.registration_config import PAPER_V2, SERVICE_DEFAULT
from pranet.engine.engine import Engine
from pranet.training.data import data_dir


def scan_poses(conf: str) -> dict[str, np.ndarray]:
    poses = {}
    for line in open(conf):
        p = line.split()
        if p and p[0] == "bmesh":
            T = np.eye(4)
            T[:3, :3] = Rotation.from_quat(np.array(p[5:9], float)).as_matrix().T
            T[:3, 3] = np.array(p[2:5], float)
            poses[p[1]] = T
    return poses


def pairs(scans):
    poses = scan_poses(str(scans / "bun.conf"))
    for src in ("bun045.ply", "bun090.ply"):
        T = np.linalg.inv(poses["bun000.ply"]) @ poses[src]
        yield f"bunny {src[:6]} -> bun000", scans / src, scans / "bun000.ply", T, 1000.0, "mm"
    T = np.loadtxt(scans / "3dmatch_gt.txt")
    yield "3DMatch src -> ref", scans / "3dmatch_src.ply", scans / "3dmatch_ref.ply", T, 100.0, "cm"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=None)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    engine = Engine.load(args.model, threads=args.threads)
    model = engine.scorer
    modes = {"v2 (60 steps + ICP)": PAPER_V2, "service default": SERVICE_DEFAULT}
    print(f"model {model.info()['name']} {model.info()['version']} ({model.info()['sha256'][:12]})")
    print("| pair | points | mode | rot err (°) | trans err | agent rot err (°) | confidence | ms | where (ms) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for name, src_path, tgt_path, T_gt, unit, unit_name in pairs(data_dir() / "scans"):
        source, target = read_point_cloud(src_path), read_point_cloud(tgt_path)
        rot0, trans0 = isotropic_errors(np.eye(4), T_gt)
        sizes = f"{len(source)} / {len(target)}"
        print(f"| {name} | {sizes} | initial | {rot0:.2f} | {trans0 * unit:.1f} {unit_name} | | | | |")
        for mode, config in modes.items():
            engine.register(source, target, config, 0)  # warm (caches, pages)
            t0 = time.perf_counter()
            reg = engine.register(source, target, config, 0)
            ms = (time.perf_counter() - t0) * 1e3
            rot, trans = isotropic_errors(reg.T_target_source, T_gt)
            agent_rot, _ = isotropic_errors(reg.agent_T_target_source, T_gt)
            where = ", ".join(f"{k} {v:.0f}" for k, v in reg.timing_ms.items() if k != "total" and v >= 0.5)
            conf = f"{reg.confidence.score:.2f} ({reg.confidence.status})" if reg.confidence else ""
            rescued = f", rescued by {reg.rescued}" if reg.rescued else ""
            print(
                f"| {name} | | {mode} | {rot:.2f} | {trans * unit:.1f} {unit_name} | {agent_rot:.2f} | {conf}{rescued} "
                f"| {ms:.0f} | {where} |"
            )


if __name__ == "__main__":
    main()
