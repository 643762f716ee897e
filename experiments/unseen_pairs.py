"""Pairs the real-scan benchmark does not list, from the same files: a check against tuning on the 15 pairs.

Writes a pairs CSV (``pranet-bench scans`` format, absolute paths into the data directory) with every listed pair
the other way round (source and target swapped, the inverse ground truth: a different resampling, a different
unit frame, the other cloud's spacing) and every pair of the six bunny views that ``pairs.csv`` leaves out (their
ground truth from ``bun.conf``; most of them are 125-180° apart with 1-17 % overlap, where no method is right and
every answer should read ``suspect``). With ``--crops``, also each RGB-D pair with its source cut by a plane
(keeping 60 % and 40 % of it, two fixed-seed directions each; the cut clouds are written beside the CSV): lower
overlap, as in 3DLoMatch. Backs docs/DESIGN.md, "Pairs we do not tune on".

    python experiments/unseen_pairs.py /tmp/unseen [--crops]
    pranet-bench scans /tmp/unseen/pairs.csv --methods pranet,kiss-matcher-gicp
"""

from __future__ import annotations

import argparse
import csv
import itertools
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from pranet.client.io import read_point_cloud, write_point_cloud
from pranet.core.se3 import inverse
from pranet.training.bench.scan_pairs import read_pairs
from pranet.training.data import data_dir

VIEWS = ("bun000", "bun045", "bun090", "bun180", "bun270", "bun315")
CROP_KEEP = (0.6, 0.4)  # fractions of the source kept by a plane
CROP_DIRECTIONS = 2  # per fraction
FIELDS = ("id", "source", "target", "T_target_source", "overlap", "rotation_deg", "kind")


def bunny_poses(conf: Path) -> dict[str, np.ndarray]:
    """Each scan's pose in the common frame: ``p_world = R(q)^T p + t`` (SOURCES.md: R(q) is transposed)."""
    poses = {}
    for line in conf.read_text().splitlines():
        f = line.split()
        if f and f[0] == "bmesh":
            T = np.eye(4)
            T[:3, :3] = Rotation.from_quat(np.array(f[5:9], dtype=float)).as_matrix().T
            T[:3, 3] = np.array(f[2:5], dtype=float)
            poses[Path(f[1]).stem] = T
    return poses


def row(pair_id: str, source: Path, target: Path, T: np.ndarray, overlap: str, kind: str) -> dict[str, str]:
    angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)))
    return {
        "id": pair_id,
        "source": str(source),
        "target": str(target),
        "T_target_source": " ".join(f"{x:.10g}" for x in T.ravel()),
        "overlap": overlap,
        "rotation_deg": f"{angle:.1f}",
        "kind": kind,
    }


def crops(pair, out: Path) -> list[tuple[str, Path, Path, np.ndarray]]:
    """``pair`` with its source cut by planes (``CROP_KEEP`` × ``CROP_DIRECTIONS``), the cut clouds written to
    ``out``: ``(id, source, target, T_target_source)`` each."""
    source = read_point_cloud(pair.source)
    rng = np.random.default_rng(3)
    made = []
    for keep in CROP_KEEP:
        for k in range(CROP_DIRECTIONS):
            d = rng.normal(size=3)
            kept = source[np.argsort(source @ d)[-int(keep * len(source)) :]]  # the far side along d
            pair_id = f"{pair.id}_keep{round(100 * keep)}_{k}"
            made.append((pair_id, write_point_cloud(out / f"{pair_id}.ply", kept), pair.target, pair.T_gt))
    return made


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path, help="directory for pairs.csv")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--crops", action="store_true", help="also the RGB-D pairs with the source cut by a plane")
    args = p.parse_args()
    scans = (data_dir(args.data_dir) / "scans").resolve()
    listed = read_pairs(scans / "pairs.csv")
    rows = [
        row(f"{q.id}_rev", q.target, q.source, inverse(q.T_gt), "" if q.overlap is None else f"{q.overlap:g}", q.kind)
        for q in listed
    ]
    poses = bunny_poses(scans / "bun.conf")
    ids = {q.id for q in listed}
    for a, b in itertools.combinations(VIEWS, 2):
        if f"bunny_{a}_to_{b}" not in ids:
            T = inverse(poses[b]) @ poses[a]
            rows.append(row(f"bunny_{a}_to_{b}", scans / f"{a}.ply", scans / f"{b}.ply", T, "", listed[0].kind))
    args.out.mkdir(parents=True, exist_ok=True)
    if args.crops:
        rows += [row(*crop, "", q.kind) for q in listed if "RGB-D" in q.kind for crop in crops(q, args.out)]
    with open(args.out / "pairs.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    print(f"{len(rows)} pairs -> {args.out / 'pairs.csv'}")


if __name__ == "__main__":
    main()
