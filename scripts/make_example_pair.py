"""Make the example pair shipped in ``examples/bunny`` from the full Stanford bunny scans.

    python scripts/make_example_pair.py [--scans ../shared/data/scans] [--out examples/bunny] [--voxel 0.0025]

Source ``bun045``, target ``bun000``: each scan is reduced to the centroids of a voxel grid (2.5 mm cells,
about 4700 of its 40000 points; Open3D's ``voxel_down_sample``, no random step, so the same input gives the
same files) and written as a binary little-endian PLY, still in metres and in the scan's own frame. The
ground truth ``T_target_source.txt`` is the inverse of ``pairs.csv``'s ``bun000 -> bun045`` row
(``target ≈ R @ source + t``): voxel centroids stay in their scan's frame, so the full scans' pose holds.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from pranet.client.io import read_point_cloud
from pranet.training.data import data_dir

SOURCE, TARGET = "bun045.ply", "bun000.ply"
VOXEL_M = 0.0025
HEADER = (
    "T_target_source of the example pair (source bun045.ply, target bun000.ply), 4x4, row-major:\n"
    "target ≈ R @ source + t, in metres. The inverse of the bun000 -> bun045 row of the scans' pairs.csv\n"
    "(from the Stanford bun.conf poses). Read it with numpy.loadtxt."
)


def listed_pose(pairs_csv: Path, source: str, target: str) -> np.ndarray:
    """``T_target_source`` for ``source -> target`` from ``pairs.csv``, inverting the row listed the other way."""
    with open(pairs_csv, newline="") as f:
        for row in csv.DictReader(f):
            T = np.array(row["T_target_source"].split(), float).reshape(4, 4)
            if (row["source"], row["target"]) == (source, target):
                return T
            if (row["source"], row["target"]) == (target, source):
                return np.linalg.inv(T)
    raise SystemExit(f"{pairs_csv}: no row for {source} -> {target} in either direction")


def voxel_centroids(points: np.ndarray, voxel: float) -> np.ndarray:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    return np.asarray(cloud.voxel_down_sample(voxel).points)


def write_binary_ply(path: Path, points: np.ndarray) -> None:
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
    if not o3d.io.write_point_cloud(str(path), cloud, write_ascii=False):
        raise SystemExit(f"{path}: Open3D could not write it")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scans", type=Path, default=None, help="default: $PRANET_DATA_DIR/scans (../shared/data/scans)")
    ap.add_argument("--out", type=Path, default=Path("examples/bunny"))
    ap.add_argument("--voxel", type=float, default=VOXEL_M, help="voxel grid cell, metres")
    args = ap.parse_args()
    scans = args.scans or data_dir() / "scans"
    args.out.mkdir(parents=True, exist_ok=True)
    for name in (SOURCE, TARGET):
        full = read_point_cloud(scans / name)
        reduced = voxel_centroids(full, args.voxel)
        write_binary_ply(args.out / name, reduced)
        print(f"{args.out / name}: {len(reduced)} of {len(full)} points ({args.voxel * 1e3:g} mm voxel grid)")
    T = listed_pose(scans / "pairs.csv", SOURCE, TARGET)
    np.savetxt(args.out / "T_target_source.txt", T, fmt="%.10f", header=HEADER, encoding="utf-8")
    print(f"{args.out / 'T_target_source.txt'}: {np.degrees(np.arccos((np.trace(T[:3, :3]) - 1) / 2)):.1f} deg")


if __name__ == "__main__":
    main()
