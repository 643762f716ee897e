"""How well candidate confidence measures tell right from wrong ICP results on the real scan pairs.

    python experiments/confidence_probe.py [--pairs-csv PATH] [--only SUBSTRING] [--out confidence_probe.json]

For every pair of the real-scan ``pairs.csv`` (``$PRANET_DATA_DIR/scans`` by default): ICP (the service's, at the
data's resolution) from the truth, from the truth turned 6-24°, and from uniformly random rotations about the
centroids; each result is judged right or wrong by the benchmark's thresholds (objects 2° / 3 mm, scenes 15° /
30 cm), and for 2048 fixed-seed query points of each cloud it records the fraction within 0.5-12 spacings of the
other cloud (global spacing, and multiples of each point's own 1st / 4th / 8th neighbour distance). The summary
prints, per tolerance / overlap-radius pair, the lowest score of a right result and the highest of a wrong one,
per pair. Backs docs/DESIGN.md, "A confidence for partial scans".
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from pranet.client.io import read_point_cloud
from pranet.core.metrics import isotropic_errors
from pranet.core.nearest import subsample
from pranet.core.registration_context import prepare
from pranet.engine.icp import make_icp
from pranet.training.data import data_dir

TOLERANCES = (1.0, 1.5, 2.0, 3.0)  # spacings
RADII = (4.0, 6.0, 8.0, 12.0)  # spacings
TRIALS = 12  # per pair: the truth, 4 turned, 7 random


def right(T: np.ndarray, T_true: np.ndarray, kind: str) -> bool:
    rot, trans = isotropic_errors(T, T_true)
    return (rot < 2.0 and trans < 0.003) if "object" in kind else (rot < 15.0 and trans < 0.3)


def starts(T_true_unit: np.ndarray, src: np.ndarray, tgt: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
    """The truth, the truth turned 6-24°, and random rotations about the centroids (unit frame)."""
    out = [T_true_unit]
    for k in range(1, TRIALS):
        if k <= 4:
            axis = rng.normal(size=3)
            R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(6 * k)).as_matrix() @ T_true_unit[:3, :3]
        else:
            R = Rotation.random(random_state=rng).as_matrix()
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, tgt.mean(axis=0) - R @ src.mean(axis=0)
        out.append(T)
    return out


def fractions(d: np.ndarray, scale: np.ndarray | float) -> dict[str, float]:
    return {
        f"{a},{b}": [float(np.mean(d <= a * scale)), float(np.mean(d <= b * scale))] for a in TOLERANCES for b in RADII
    }


def probe(pairs_csv: Path, only: str) -> list[dict]:
    icp = make_icp()
    rng = np.random.default_rng(0)
    records = []
    for row in csv.DictReader(pairs_csv.open()):
        if only not in row["id"]:
            continue
        source = read_point_cloud(pairs_csv.parent / row["source"])
        target = read_point_cloud(pairs_csv.parent / row["target"])
        T_true = np.array(row["T_target_source"].split(), dtype=float).reshape(4, 4)
        c = prepare(source, target, 256, np.random.default_rng(0))
        S, T_ = c.src_unit, c.tgt_unit
        tree_s, tree_t = cKDTree(S), cKDTree(T_)
        q_s, q_t = subsample(S, 2048, 2), subsample(T_, 2048, 3)
        local_s, local_t = tree_s.query(q_s, k=9)[0], tree_t.query(q_t, k=9)[0]  # own neighbour distances
        for start in starts(c.norm.transform_to_unit(T_true), S, T_, rng):
            T = icp(S, T_, start, c.resolution).transform
            inv = np.linalg.inv(T)
            d_s = tree_t.query(q_s @ T[:3, :3].T + T[:3, 3])[0]
            d_t = tree_s.query(q_t @ inv[:3, :3].T + inv[:3, 3])[0]
            rec = {"id": row["id"], "right": right(c.norm.transform_to_world(T), T_true, row["kind"])}
            for name, (ss, st) in {
                "g": (c.resolution.spacing,) * 2,
                "k1": (local_s[:, 1], local_t[:, 1]),
                "k4": (local_s[:, 4], local_t[:, 4]),
                "k8": (local_s[:, 8], local_t[:, 8]),
            }.items():
                rec[name] = {"source": fractions(d_s, ss), "target": fractions(d_t, st)}
            records.append(rec)
        print(row["id"], flush=True)
    return records


def score(rec: dict, scale: str, key: str) -> float:
    """min over directions of (within tolerance) / (within radius), scaled down under 10 % overlap."""
    (fs, ns), (ft, nt) = rec[scale]["source"][key], rec[scale]["target"][key]
    return min(fs / max(ns, 1e-9), ft / max(nt, 1e-9)) * min(1.0, min(ns, nt) / 0.1)


def summarize(records: list[dict]) -> None:
    for scale in ("g", "k1", "k4", "k8"):
        for a in TOLERANCES:
            for b in RADII:
                key = f"{a},{b}"
                right_scores = [score(r, scale, key) for r in records if r["right"]]
                wrong_scores = [score(r, scale, key) for r in records if not r["right"]]
                if right_scores and wrong_scores:
                    print(f"{scale} {key}: lowest right {min(right_scores):.2f}, highest wrong {max(wrong_scores):.2f}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs-csv", type=Path, default=data_dir() / "scans" / "pairs.csv")
    p.add_argument("--only", default="", help="pairs whose id contains this")
    p.add_argument("--out", type=Path, default=Path("confidence_probe.json"))
    args = p.parse_args()
    records = probe(args.pairs_csv, args.only)
    args.out.write_text(json.dumps(records))
    summarize(records)


if __name__ == "__main__":
    main()
