"""Finishes of a partial-overlap registration, from the true pose: how precise each ends (1° / 0.01 right, and the
median rotation error). Per pair of pranet-bench's first N unseen-category pairs of a setting: the service's ICP
stages with their kernel, then each finish. Backs docs/DESIGN.md, "A sharper finish".

    python experiments/finish_probe.py --setting partial --pairs 100
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial.transform import Rotation

from pranet.core.metrics import SUCCESS_ROTATION_DEG, SUCCESS_TRANSLATION, isotropic_errors
from pranet.core.nearest import PointIndex
from pranet.core.registration_config import DEFAULT_ICP_STAGES, ICP_KERNEL
from pranet.core.registration_context import prepare
from pranet.core.robust_icp import symmetric_robust_icp, tukey_weights
from pranet.core.se3 import apply_transform, inverse
from pranet.engine.icp import make_icp
from pranet.training.bench.records import as_float32, pair_seed
from pranet.training.data import data_dir, load_modelnet40, test_indices
from pranet.training.samples import make_pair, pair_rng


def normals(index: PointIndex, k: int) -> np.ndarray:
    """Unoriented PCA normals of each point from its ``k`` nearest neighbours."""
    _, idx = index.neighbours(index.points, k)
    nb = index.points[idx] - index.points[idx].mean(1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    return vecs[:, :, 0]


def small_motion(rows: np.ndarray, residual: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The 4x4 of the weighted least-squares twist ``rows @ [ω, v] ≈ -residual`` (linearised)."""
    A = rows * w[:, None]
    x = np.linalg.lstsq(A.T @ rows + 1e-9 * np.eye(6), -(A.T @ residual), rcond=None)[0]
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
    T[:3, 3] = x[3:]
    return T


def symmetric_plane_icp(src: PointIndex, tgt: PointIndex, T0, scale: float, k: int, iters: int = 30) -> np.ndarray:
    """Both directions point-to-plane (each point to its nearest neighbour's plane), Tukey on the point distance."""
    n_s, n_t = normals(src, k), normals(tgt, k)
    T = np.asarray(T0, dtype=np.float64).copy()
    for _ in range(iters):
        p = apply_transform(T, src.points)
        d_s, j_s = tgt.neighbours(p, 1)
        d_t, j_t = src.neighbours(apply_transform(inverse(T), tgt.points), 1)
        # residuals in the target frame: source point p vs target plane (q, n_q); target point q vs moved source plane
        q1, n1 = tgt.points[j_s[:, 0]], n_t[j_s[:, 0]]
        p2 = p[j_t[:, 0]]
        n2 = n_s[j_t[:, 0]] @ T[:3, :3].T
        q2 = tgt.points
        P = np.vstack([p, p2])
        Q = np.vstack([q1, q2])
        N = np.vstack([n1, n2])
        w = np.concatenate([tukey_weights(d_s[:, 0], scale), tukey_weights(d_t[:, 0], scale)])
        if not w.any():
            return T
        rows = np.hstack([np.cross(P, N), N])
        res = ((P - Q) * N).sum(1)
        step = small_motion(rows, res, w)
        T = step @ T
        if np.abs(step - np.eye(4)).max() < 1e-6:
            break
    return T


def one_way_plane_icp(src: PointIndex, tgt: PointIndex, T0, scale: float, k: int, iters: int = 30) -> np.ndarray:
    n_t = normals(tgt, k)
    T = np.asarray(T0, dtype=np.float64).copy()
    for _ in range(iters):
        p = apply_transform(T, src.points)
        d, j = tgt.neighbours(p, 1)
        q, n = tgt.points[j[:, 0]], n_t[j[:, 0]]
        w = tukey_weights(d[:, 0], scale)
        if not w.any():
            return T
        step = small_motion(np.hstack([np.cross(p, n), n]), ((p - q) * n).sum(1), w)
        T = step @ T
        if np.abs(step - np.eye(4)).max() < 1e-6:
            break
    return T


def symmetric_mean_icp(src: PointIndex, tgt: PointIndex, T0, scale: float, k: int, iters: int = 30) -> np.ndarray:
    """As ``symmetric_robust_icp``, each point matched to the mean of its ``k`` nearest (a local surface average),
    weighed by Tukey on the nearest one's distance."""
    from pranet.core.robust_icp import weighted_kabsch

    T = np.asarray(T0, dtype=np.float64).copy()
    for _ in range(iters):
        d_s, j_s = tgt.neighbours(apply_transform(T, src.points), k)
        d_t, j_t = src.neighbours(apply_transform(inverse(T), tgt.points), k)
        w = np.concatenate([tukey_weights(d_s[:, 0], scale), tukey_weights(d_t[:, 0], scale)])
        if not w.any():
            return T
        a = np.vstack([src.points, src.points[j_t].mean(1)])
        b = np.vstack([tgt.points[j_s].mean(1), tgt.points])
        moved = weighted_kabsch(a, b, w)
        step = float(np.abs(moved - T).max())
        T = moved
        if step < 1e-5:
            break
    return T


def boundary(index: PointIndex, k: int, threshold: float) -> np.ndarray:
    """Points on the cloud's rim: their ``k`` neighbours' centroid lies more than ``threshold`` times the neighbours'
    mean distance away from them (a neighbourhood on one side only)."""
    d, idx = index.neighbours(index.points, k + 1)
    offset = np.linalg.norm(index.points[idx[:, 1:]].mean(1) - index.points, axis=1)
    return offset > threshold * d[:, 1:].mean(1)


def symmetric_boundary_icp(src: PointIndex, tgt: PointIndex, T0, scale: float, k: int, thr: float, iters: int = 30):
    """As ``symmetric_robust_icp``, without the matches whose nearest point is on the other cloud's rim (zippering's
    rule, Turk & Levoy): a point beyond the other cloud's crop finds its nearest at that rim and pulls inward."""
    from pranet.core.robust_icp import weighted_kabsch

    rim_s, rim_t = boundary(src, k, thr), boundary(tgt, k, thr)
    T = np.asarray(T0, dtype=np.float64).copy()
    for _ in range(iters):
        d_s, j_s = tgt.neighbours(apply_transform(T, src.points), 1)
        d_t, j_t = src.neighbours(apply_transform(inverse(T), tgt.points), 1)
        w = np.concatenate(
            [tukey_weights(d_s[:, 0], scale) * ~rim_t[j_s[:, 0]], tukey_weights(d_t[:, 0], scale) * ~rim_s[j_t[:, 0]]]
        )
        if not w.any():
            return T
        a = np.vstack([src.points, src.points[j_t[:, 0]]])
        moved = weighted_kabsch(a, np.vstack([tgt.points[j_s[:, 0]], tgt.points]), w)
        step = float(np.abs(moved - T).max())
        T = moved
        if step < 1e-5:
            break
    return T


def sym(scale: float):
    return lambda c, T, s: symmetric_robust_icp(c.src_index, c.tgt_index, T, scale * s)


FINISHES = {  # name -> finish(prepared clouds, the stages' result, spacing) -> T
    "stages only": lambda c, T, s: T,
    "p2p sym 1.5 (shipped)": sym(1.5),
    "p2p sym 1.0": sym(1.0),
    "p2p sym 1.25": sym(1.25),
    "p2p sym 2.0": sym(2.0),
    "p2p sym 2.5": sym(2.5),
    "p2p sym 1.5, 100 iterations": lambda c, T, s: symmetric_robust_icp(
        c.src_index, c.tgt_index, T, 1.5 * s, 100, 1e-7
    ),
    "p2p sym 1.5 then 0.75": lambda c, T, s: sym(0.75)(c, sym(1.5)(c, T, s), s),
    "p2p sym 1.5, 3 neighbours' mean": lambda c, T, s: symmetric_mean_icp(c.src_index, c.tgt_index, T, 1.5 * s, 3),
    "p2p sym 1.5, 5 neighbours' mean": lambda c, T, s: symmetric_mean_icp(c.src_index, c.tgt_index, T, 1.5 * s, 5),
    "plane sym 1.5 k10": lambda c, T, s: symmetric_plane_icp(c.src_index, c.tgt_index, T, 1.5 * s, 10),
    "plane sym 2.5 k16": lambda c, T, s: symmetric_plane_icp(c.src_index, c.tgt_index, T, 2.5 * s, 16),
    "p2p 1.5 then plane sym 1.5 k10": lambda c, T, s: symmetric_plane_icp(
        c.src_index, c.tgt_index, sym(1.5)(c, T, s), 1.5 * s, 10
    ),
    "plane one-way 1.5 k10": lambda c, T, s: one_way_plane_icp(c.src_index, c.tgt_index, T, 1.5 * s, 10),
    "no rim matches, k10, 0.6": lambda c, T, s: symmetric_boundary_icp(c.src_index, c.tgt_index, T, 1.5 * s, 10, 0.6),
    "no rim matches, k10, 0.8": lambda c, T, s: symmetric_boundary_icp(c.src_index, c.tgt_index, T, 1.5 * s, 10, 0.8),
    "no rim matches, k16, 0.6": lambda c, T, s: symmetric_boundary_icp(c.src_index, c.tgt_index, T, 1.5 * s, 16, 0.6),
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--setting", default="partial")
    p.add_argument("--pairs", type=int, default=100)
    p.add_argument("--offset", type=int, default=0, help="first pair")
    p.add_argument("--turn", type=float, default=0.0, help="degrees the start is turned off the truth")
    p.add_argument("--finishes", default="", help="comma-separated names of FINISHES (default: all)")
    args = p.parse_args()
    stages = make_icp(DEFAULT_ICP_STAGES, kernel=ICP_KERNEL)
    finishes = {name: FINISHES[name] for name in (args.finishes.split(",") if args.finishes else FINISHES)}
    errs: dict[str, list[tuple[float, float]]] = {name: [] for name in finishes}
    secs = dict.fromkeys(finishes, 0.0)
    data = load_modelnet40(data_dir(None), "test")
    rng = np.random.default_rng(0)
    for i, j in enumerate(test_indices(data.labels)[args.offset : args.offset + args.pairs], start=args.offset):
        pair = as_float32(make_pair(data.points[j], args.setting, pair_rng(0, args.setting, i), 60.0, 0.5))
        c = prepare(pair.source, pair.target, 256, np.random.default_rng(pair_seed(0, args.setting, i)))
        start = c.norm.transform_to_unit(pair.T_gt)
        if args.turn:
            axis = rng.normal(size=3)
            turn = np.eye(4)
            turn[:3, :3] = Rotation.from_rotvec(np.deg2rad(args.turn) * axis / np.linalg.norm(axis)).as_matrix()
            start = turn @ start
        staged = stages(c.src_unit, c.tgt_unit, start, c.resolution).transform
        for name, finish in finishes.items():
            t0 = time.perf_counter()
            T = finish(c, staged, c.resolution.spacing)
            secs[name] += time.perf_counter() - t0
            errs[name].append(isotropic_errors(c.norm.transform_to_world(T), pair.T_gt))
    print(f"{args.setting}, pairs {args.offset}-{args.offset + args.pairs - 1}, start turned {args.turn:g}°")
    print(f"  {'finish':34s} right  rot med  rot p90  trans med  ms/pair")
    for name, e in errs.items():
        a = np.array(e)
        right = int(((a[:, 0] < SUCCESS_ROTATION_DEG) & (a[:, 1] < SUCCESS_TRANSLATION)).sum())
        print(
            f"  {name:34s} {right:5d}  {np.median(a[:, 0]):7.3f}  {np.percentile(a[:, 0], 90):7.3f}"
            f"  {np.median(a[:, 1]):9.4f}  {1000 * secs[name] / len(a):7.1f}"
        )


if __name__ == "__main__":
    main()
