"""The classical peers of ``pranet-bench scans``, each at the data's own resolution.

Every peer takes ``(source, target, voxel, seed)`` (world units, ``(N, 3)`` float64) and returns
``T_target_source`` (4x4, ``target ≈ R @ source + t``); the voxel is the same for every method of a pair
(``scan_voxel``). Each is the strongest configuration we found of a short, documented recipe:

- ``open3d_ransac_icp``: voxel grid, KNN-30 normals, FPFH at 5 voxels, Open3D's feature RANSAC (100k
  iterations, confidence 0.999, edge-length and distance checkers at 1.5 voxels), point-to-plane ICP at 2, 1 and
  ½ voxel;
- ``kiss_matcher_gicp``: KISS-Matcher (its default gains: normals at 3, FPFH at 5 voxels; ROBIN + GNC), then
  small_gicp GICP at 1 then ½ voxel;
- ``fgr_icp``: the same FPFH, Open3D's fast global registration, the same point-to-plane ICP.

Threads: small_gicp takes ``threads``; Open3D's OpenMP reads ``OMP_NUM_THREADS`` once, at import (``pranet-bench``
sets it to ``--threads`` first); KISS-Matcher's TBB takes every core.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from pranet.core.resolution import median_spacing
from pranet.core.se3 import Array

SPACING_SAMPLES = 2000  # source points whose nearest neighbour sets the spacing (a fixed-seed subsample)
VOXEL_PER_SPACING = 4.0  # voxel = 4 x the median point spacing: FPFH needs a few neighbours per voxel radius
NORMAL_KNN = 30
FPFH_RADIUS = 5.0  # voxels
FPFH_MAX_NN = 100
RANSAC_ITERATIONS = 100_000
RANSAC_CONFIDENCE = 0.999
RANSAC_CHECK_DISTANCE = 1.5  # voxels: the inlier distance and the distance checker
EDGE_LENGTH_RATIO = 0.9
# voxels: point-to-plane ICP, coarse then fine. The ½-voxel pass is ours, beyond the "2 then 1": on the
# voxel grid a 1-voxel window still pulls in the edge of the overlap, which left bun090 -> bun180 (31 % overlap) at
# 2.0° / 2.5 mm even from the true pose; at ½ voxel it lands at 0.2° / 0.3 mm, no rotation gets worse by more than
# 0.02° and no object translation by more than 0.05 mm (the GICP peer ends at ½ voxel too). docs/DESIGN.md,
# "Real-scan benchmark".
ICP_WINDOWS = (2.0, 1.0, 0.5)
GICP_WINDOWS = (1.0, 0.5)  # voxels: small_gicp GICP after KISS-Matcher
ICP_MAX_ITERATIONS = 50

PeerFn = Callable[[Array, Array, float, int, int], Array]  # (source, target, voxel, seed, threads) -> T


def point_spacing(points: Array, seed: int = 0, samples: int = SPACING_SAMPLES) -> float:
    """Median distance from a point to its nearest other point, over ``samples`` points drawn with ``seed``
    (against the whole cloud): the pipeline's own measure, ``core.resolution.median_spacing``, so that the peers'
    voxel is the one the service would derive from the same cloud."""
    spacing = median_spacing(np.asarray(points, dtype=np.float64), probes=samples, seed=seed)
    if spacing <= 0:
        raise ValueError("cannot measure the point spacing: every sampled point is duplicated")
    return spacing


def scan_voxel(source: Array, seed: int = 0) -> float:
    """The voxel every method of a pair runs at: 4x the source's median point spacing."""
    return VOXEL_PER_SPACING * point_spacing(source, seed)


# --- Open3D: features, RANSAC, FGR, point-to-plane ICP ------------------------------------------------------


def _cloud(points: Array) -> Any:
    import open3d as o3d

    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
    return pc


def features(points: Array, voxel: float) -> tuple[Any, Any]:
    """The cloud on a ``voxel`` grid with KNN normals, and its FPFH at 5 voxels."""
    import open3d as o3d

    down = _cloud(points).voxel_down_sample(voxel)
    down.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_KNN))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        down, o3d.geometry.KDTreeSearchParamHybrid(radius=FPFH_RADIUS * voxel, max_nn=FPFH_MAX_NN)
    )
    return down, fpfh


def point_to_plane_icp(source_down: Any, target_down: Any, T: Array, voxel: float) -> Array:
    """Point-to-plane ICP from ``T`` within 2 voxels, then 1, then ½ (the clouds carry normals)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    for window in ICP_WINDOWS:
        T = reg.registration_icp(
            source_down,
            target_down,
            window * voxel,
            T,
            reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(max_iteration=ICP_MAX_ITERATIONS),
        ).transformation
    return np.asarray(T, dtype=np.float64).copy()


def ransac(source_down: Any, target_down: Any, source_fpfh: Any, target_fpfh: Any, voxel: float, seed: int) -> Array:
    """Open3D's feature-matching RANSAC, seeded (``o3d.utility.random.seed``) so a pair gives one answer."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    o3d.utility.random.seed(seed)
    distance = RANSAC_CHECK_DISTANCE * voxel
    result = reg.registration_ransac_based_on_feature_matching(
        source_down,
        target_down,
        source_fpfh,
        target_fpfh,
        mutual_filter=False,
        max_correspondence_distance=distance,
        estimation_method=reg.TransformationEstimationPointToPoint(False),
        ransac_n=3,
        checkers=[
            reg.CorrespondenceCheckerBasedOnEdgeLength(EDGE_LENGTH_RATIO),
            reg.CorrespondenceCheckerBasedOnDistance(distance),
        ],
        criteria=reg.RANSACConvergenceCriteria(RANSAC_ITERATIONS, RANSAC_CONFIDENCE),
    )
    return np.asarray(result.transformation, dtype=np.float64).copy()


def open3d_ransac_icp(source: Array, target: Array, voxel: float, seed: int, threads: int = 2) -> Array:
    """The tuned Open3D pipeline: FPFH + RANSAC, then point-to-plane ICP at 2, 1 and ½ voxel."""
    src, src_f = features(source, voxel)
    tgt, tgt_f = features(target, voxel)
    return point_to_plane_icp(src, tgt, ransac(src, tgt, src_f, tgt_f, voxel, seed), voxel)


def fgr_icp(source: Array, target: Array, voxel: float, seed: int, threads: int = 2) -> Array:
    """FPFH + Open3D's fast global registration (deterministic: ``seed`` is unused), then the same ICP."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    src, src_f = features(source, voxel)
    tgt, tgt_f = features(target, voxel)
    coarse = reg.registration_fgr_based_on_feature_matching(
        src, tgt, src_f, tgt_f, reg.FastGlobalRegistrationOption(maximum_correspondence_distance=0.5 * voxel)
    ).transformation
    return point_to_plane_icp(src, tgt, np.asarray(coarse), voxel)


# --- KISS-Matcher + small_gicp ------------------------------------------------------------------------------


def kiss_matcher(source: Array, target: Array, voxel: float) -> Array:
    """KISS-Matcher's global estimate at ``voxel`` (its own voxel grid, FPFH, ROBIN pruning, GNC solver).

    It runs in voxel units (both clouds divided by ``voxel``): its configuration refuses voxels under 5 mm (a
    range scan of a small object has 2 mm) and clamps its noise bounds at 1.0 world unit, so in world units it is
    not scale-free; in voxel units every distance it uses is its documented gain times the voxel."""
    import kiss_matcher as km

    matcher = km.KISSMatcher(km.KISSMatcherConfig(voxel_size=1.0))
    sol = matcher.estimate(np.asarray(source / voxel, dtype=np.float32), np.asarray(target / voxel, dtype=np.float32))
    T = np.eye(4)
    T[:3, :3] = np.asarray(sol.rotation, dtype=np.float64)
    T[:3, 3] = np.asarray(sol.translation, dtype=np.float64).ravel() * voxel
    return T


def gicp(source: Array, target: Array, T: Array, voxel: float, threads: int = 2) -> Array:
    """small_gicp GICP from ``T`` on clouds downsampled at ``voxel``, within 1 then ½ voxel."""
    import small_gicp

    src, tgt = np.ascontiguousarray(source, dtype=np.float64), np.ascontiguousarray(target, dtype=np.float64)
    for window in GICP_WINDOWS:
        T = small_gicp.align(
            tgt,
            src,
            init_T_target_source=T,
            registration_type="GICP",
            downsampling_resolution=voxel,
            max_correspondence_distance=window * voxel,
            num_threads=threads,
            # its default stops at 1e-3 world units: a millimetre on object scans, not fine enough
            translation_epsilon=1e-3 * voxel,
        ).T_target_source
    return np.asarray(T, dtype=np.float64).copy()


def kiss_matcher_gicp(source: Array, target: Array, voxel: float, seed: int, threads: int = 2) -> Array:
    """KISS-Matcher (deterministic: ``seed`` is unused), then small_gicp GICP at 1 and ½ voxel."""
    return gicp(source, target, kiss_matcher(source, target, voxel), voxel, threads)


PEERS: dict[str, PeerFn] = {
    "open3d-ransac-icp": open3d_ransac_icp,
    "kiss-matcher-gicp": kiss_matcher_gicp,
    "fgr-icp": fgr_icp,
}
