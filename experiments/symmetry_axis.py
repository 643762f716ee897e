"""About which axis the agent's far-off answers are turned: the shape's own symmetry axis, or any.

For every pair of a `pranet-eval --json` file that a method ends more than ``--min-deg`` off, the residual rotation
``R_gtᵀ R_est`` (in the source's frame) is compared with the shape's candidate symmetry axis: the principal axis whose
covariance eigenvalue stands farthest from the other two, about which the shape is round when those two are equal
(``roundness``: their ratio, 1 for a body of revolution). An answer turned about that axis is a turned copy of the
shape that no pose-blind measure of fit tells from the truth; one turned about another axis is plainly misaligned.

    python experiments/symmetry_axis.py results/eval-clean-fine.json.gz --method pranet-v1
"""

from __future__ import annotations

import argparse
import gzip
import json
from collections import Counter
from pathlib import Path

import numpy as np

from pranet.training.data import data_dir, load_modelnet40


def rotation_axis_angle(R: np.ndarray) -> tuple[np.ndarray, float]:
    """The unit axis and the angle (degrees) of the rotation ``R``."""
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w / max(np.linalg.norm(w), 1e-12), angle


def symmetry_axis(points: np.ndarray) -> tuple[np.ndarray, float]:
    """The principal axis whose eigenvalue is farthest from the other two, and the ratio of those two (≤ 1)."""
    ev, V = np.linalg.eigh(np.cov((points - points.mean(axis=0)).T))
    gap = [min(abs(ev[i] - ev[j]) for j in range(3) if j != i) for i in range(3)]
    k = int(np.argmax(gap))
    others = [ev[j] for j in range(3) if j != k]
    return V[:, k], float(min(others) / max(others))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("eval_json", type=Path)
    p.add_argument("--method", default="pranet-v1")
    p.add_argument("--min-deg", type=float, default=10.0)
    p.add_argument("--data-dir")
    args = p.parse_args()
    opener = gzip.open if args.eval_json.suffix == ".gz" else open
    with opener(args.eval_json, "rt") as f:
        records = json.load(f)["records"][args.method]
    data = load_modelnet40(data_dir(args.data_dir), "test")
    names = (data.files[0].parent / "shape_names.txt").read_text().split()
    rows = []
    for r in records:
        if r["rotation_deg"] <= args.min_deg:
            continue
        shape = data.points[r["shape"]].astype(np.float64)
        axis, angle = rotation_axis_angle(np.array(r["T_gt"])[:3, :3].T @ np.array(r["T_est"])[:3, :3])
        sym, roundness = symmetry_axis(shape)
        off = float(np.degrees(np.arccos(min(1.0, abs(float(axis @ sym))))))
        rows.append((names[data.labels[r["shape"]]], angle, off, roundness))
    print(f"{args.method}: {len(rows)} of {len(records)} pairs more than {args.min_deg:g}° off")
    print("| category | pairs | residual turn, median | its axis from the symmetry axis, median | roundness, median |")
    print("| --- | --- | --- | --- | --- |")
    for name, n in Counter(r[0] for r in rows).most_common():
        sel = np.array([r[1:] for r in rows if r[0] == name])
        turn, off, roundness = np.median(sel, axis=0)
        print(f"| {name} | {n} | {turn:.1f}° | {off:.1f}° | {roundness:.2f} |")
    off = np.array([r[2] for r in rows])
    print(
        f"axis within 10° of the symmetry axis: {int((off <= 10).sum())} of {len(rows)}; "
        f"median {np.median(off):.1f}° (a random axis: median 60°)"
    )


if __name__ == "__main__":
    main()
