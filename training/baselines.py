"""Classical baselines for ``pranet-eval``: ICP, FGR + ICP and RANSAC + ICP, all with Open3D (0.18-0.20).

Every baseline is ``fn(source (N, 3), target (M, 3), seed) -> (4, 4) T_target_source`` (``target ≈ R @
source + t``). ``seed`` is an int, a ``numpy.random.Generator`` (one int is drawn from it) or ``None``;
it seeds Open3D's global generator (``o3d.utility.random.seed``) before each call, so RANSAC is
reproducible. The defaults assume the ModelNet40 unit frame (shapes inside the unit sphere).

Defaults (stated, since the paper only names "Open3D 0.9.0 implementations"):

- ``icp``: point-to-point ICP from the identity, max correspondence distance ``ICP_MAX_DISTANCE`` =
  0.5, up to 100 iterations (convergence tolerances 1e-6). This is the ``ICP`` row of the tables. The
  test translations reach 0.5 per axis (offsets up to 0.87), so a 0.05-0.1 window finds almost no
  correspondences from the identity: on the first 300 noisy test pairs (seed 1234) the success rate
  was 16 % at 0.1, 56 % at 0.15, 78 % at 0.2, 85 % at 0.3 and 87 % at 0.5 (mean rotation error 34°,
  20°, 12.6°, 9.0°, 7.6°; the paper's ICP: 6.4°). 0.5 is the strongest of these, so the baseline
  is not handicapped; ``pranet-eval --icp-distance`` changes it.
- ``fgr_icp``: voxel 0.05 down-sampling, normals by PCA over the 30 nearest neighbours (``KNN(30)``,
  no radius; oriented away from the centroid: our data has no mesh normals, the paper's FGR* had clean
  ones), FPFH (radius 0.25 = 5 voxels, at most 100 neighbours), ``registration_fgr_based_on_feature_matching``
  (default options; max correspondence distance 0.025), then the refinement ICP.

  Normals decide these two baselines. After down-sampling a noisy 512-point cloud keeps ~490 points,
  so a radius-0.1 neighbourhood (the tutorial's 2 voxels) holds only a few points and the normals, and
  with them FPFH, are noise: FGR+ICP then succeeded on 15 % of 60 noisy pairs, with ``KNN(30)`` on
  83 %. A wider FPFH radius helps further on noisy pairs (0.5: FGR 97 %, RANSAC 97 % on pairs
  100-159) but we keep Open3D's usual 5 voxels (``FPFH_RADIUS``) rather than tune on the test set.
- ``ransac_icp``: the same features, ``registration_ransac_based_on_feature_matching`` without the
  mutual filter, point-to-point estimation on 3 correspondences, distance threshold 0.075,
  edge-length (0.9) and distance (0.075) checkers, ``RANSACConvergenceCriteria(100000, 0.999)``, then
  the refinement ICP.
- refinement ICP (after FGR / RANSAC): point-to-point, max correspondence distance
  ``REFINE_MAX_DISTANCE`` = 0.05 (the distance PRANet-v2's ICP uses, ``pranet.engine.icp``), 100
  iterations, on the full (not down-sampled) clouds.

Seeded RANSAC gave bit-identical transforms across runs with ``OMP_NUM_THREADS`` 1 and 2 (Open3D
0.20); Open3D does not promise this for every thread count.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]
Seed = int | np.random.Generator | None
BaselineFn = Callable[[npt.ArrayLike, npt.ArrayLike, Seed], Array]

ICP_MAX_DISTANCE = 0.5
REFINE_MAX_DISTANCE = 0.05
ICP_MAX_ITERATIONS = 100
VOXEL = 0.05
NORMAL_KNN = 30
FPFH_RADIUS = 5 * VOXEL
FPFH_MAX_NN = 100
FGR_MAX_DISTANCE = 0.5 * VOXEL
RANSAC_DISTANCE = 1.5 * VOXEL
RANSAC_MAX_ITERATIONS = 100_000
RANSAC_CONFIDENCE = 0.999
EDGE_LENGTH_RATIO = 0.9


def _o3d():
    import open3d as o3d

    return o3d


def seed_open3d(seed: Seed) -> int | None:
    """Seed Open3D's global generator; returns the int used (``None``: left as it is)."""
    if seed is None:
        return None
    value = int(seed.integers(0, 2**31 - 1)) if isinstance(seed, np.random.Generator) else int(seed)
    _o3d().utility.random.seed(value)
    return value


def to_cloud(points: npt.ArrayLike):  # -> open3d.geometry.PointCloud
    o3d = _o3d()
    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.ascontiguousarray(np.asarray(points, dtype=np.float64)))
    return pc


def estimate_normals(pc, knn: int = NORMAL_KNN) -> None:
    """PCA normals over the ``knn`` nearest neighbours, flipped to point away from the centroid.

    The ModelNet40 files we use have no normals, so FGR and RANSAC run on these estimates (the paper's
    FGR* had clean mesh normals).
    """
    o3d = _o3d()
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn))
    pts = np.asarray(pc.points)
    n = np.asarray(pc.normals)
    flip = np.einsum("ij,ij->i", n, pts - pts.mean(axis=0)) < 0
    n[flip] *= -1.0
    pc.normals = o3d.utility.Vector3dVector(n)


def fpfh(points: npt.ArrayLike, voxel: float = VOXEL, radius: float | None = None):
    """``(down-sampled cloud with normals, its FPFH features)``; FPFH radius ``radius`` (default 5 voxels)."""
    o3d = _o3d()
    down = to_cloud(points).voxel_down_sample(voxel)
    estimate_normals(down)
    feats = o3d.pipelines.registration.compute_fpfh_feature(
        down, o3d.geometry.KDTreeSearchParamHybrid(radius=radius or 5 * voxel, max_nn=FPFH_MAX_NN)
    )
    return down, feats


@dataclass(frozen=True)
class IcpOutcome:
    transform: Array
    fitness: float
    inlier_rmse: float


def run_icp(
    source: npt.ArrayLike,
    target: npt.ArrayLike,
    init: npt.ArrayLike | None = None,
    max_distance: float = ICP_MAX_DISTANCE,
    max_iterations: int = ICP_MAX_ITERATIONS,
) -> IcpOutcome:
    """Open3D point-to-point ICP of ``source`` onto ``target`` from ``init`` (default: the identity)."""
    reg = _o3d().pipelines.registration
    r = reg.registration_icp(
        to_cloud(source),
        to_cloud(target),
        max_distance,
        np.eye(4) if init is None else np.asarray(init, dtype=np.float64),
        reg.TransformationEstimationPointToPoint(),
        reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=max_iterations),
    )
    return IcpOutcome(np.asarray(r.transformation, dtype=np.float64).copy(), float(r.fitness), float(r.inlier_rmse))


def icp(
    source: npt.ArrayLike, target: npt.ArrayLike, seed: Seed = None, max_distance: float = ICP_MAX_DISTANCE
) -> Array:
    """Point-to-point ICP from the identity (deterministic; ``seed`` is accepted for a uniform signature)."""
    del seed
    return run_icp(source, target, None, max_distance).transform


def fgr(source: npt.ArrayLike, target: npt.ArrayLike, seed: Seed = None, voxel: float = VOXEL) -> Array:
    """Fast Global Registration on FPFH features (no refinement)."""
    reg = _o3d().pipelines.registration
    seed_open3d(seed)
    src, src_f = fpfh(source, voxel)
    tgt, tgt_f = fpfh(target, voxel)
    r = reg.registration_fgr_based_on_feature_matching(
        src, tgt, src_f, tgt_f, reg.FastGlobalRegistrationOption(maximum_correspondence_distance=0.5 * voxel)
    )
    return np.asarray(r.transformation, dtype=np.float64).copy()


def ransac(
    source: npt.ArrayLike,
    target: npt.ArrayLike,
    seed: Seed = None,
    voxel: float = VOXEL,
    max_iterations: int = RANSAC_MAX_ITERATIONS,
    confidence: float = RANSAC_CONFIDENCE,
) -> Array:
    """RANSAC on FPFH correspondences (no refinement)."""
    reg = _o3d().pipelines.registration
    seed_open3d(seed)
    src, src_f = fpfh(source, voxel)
    tgt, tgt_f = fpfh(target, voxel)
    distance = 1.5 * voxel
    r = reg.registration_ransac_based_on_feature_matching(
        src,
        tgt,
        src_f,
        tgt_f,
        False,  # mutual_filter
        distance,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [
            reg.CorrespondenceCheckerBasedOnEdgeLength(EDGE_LENGTH_RATIO),
            reg.CorrespondenceCheckerBasedOnDistance(distance),
        ],
        reg.RANSACConvergenceCriteria(max_iterations, confidence),
    )
    return np.asarray(r.transformation, dtype=np.float64).copy()


def fgr_icp(source: npt.ArrayLike, target: npt.ArrayLike, seed: Seed = None) -> Array:
    """FGR on FPFH features, refined by point-to-point ICP on the full clouds."""
    return run_icp(source, target, fgr(source, target, seed), REFINE_MAX_DISTANCE).transform


def ransac_icp(source: npt.ArrayLike, target: npt.ArrayLike, seed: Seed = None) -> Array:
    """RANSAC on FPFH features, refined by point-to-point ICP on the full clouds."""
    return run_icp(source, target, ransac(source, target, seed), REFINE_MAX_DISTANCE).transform


BASELINES: dict[str, BaselineFn] = {"icp": icp, "fgr": fgr_icp, "ransac": ransac_icp}
