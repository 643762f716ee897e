"""Register the bunny scans bun045 (source) -> bun000 (target) in-process and score against ``bun.conf``.

    python scripts/scan_check.py [--model DIR]

Ground truth as ``../shared/data/scans/SOURCES.md`` describes: each ``bmesh`` line maps its scan into
the common frame as ``p_world = R(q)ᵀ p + t``; ``T_target_source = inv(T_world_bun000) @ T_world_bun045``.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial.transform import Rotation

from pranet.client.io import read_point_cloud
from pranet.core.metrics import isotropic_errors
from pranet.core.pipeline import register
from pranet.model.runtime import RewardModel
from pranet.service.icp import make_icp
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=None)
    args = ap.parse_args()
    scans = data_dir() / "scans"
    poses = scan_poses(str(scans / "bun.conf"))
    T_gt = np.linalg.inv(poses["bun000.ply"]) @ poses["bun045.ply"]
    source, target = read_point_cloud(scans / "bun045.ply"), read_point_cloud(scans / "bun000.ply")
    reg = register(source, target, RewardModel.load(args.model, threads=1), np.random.default_rng(0), icp=make_icp())
    for name, T in (("initial", np.eye(4)), ("agent", reg.agent_transform), ("agent + ICP", reg.transform)):
        rot, trans = isotropic_errors(T, T_gt)
        print(f"{name:12s} rotation error {rot:6.2f}°  translation error {trans * 1000:6.1f} mm")
    print(f"confidence {reg.confidence.score:.2f} ({reg.confidence.status})" if reg.confidence else "")


if __name__ == "__main__":
    main()
