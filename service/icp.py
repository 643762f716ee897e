"""ICP refinement with Open3D (PRANet-v2), in the model's unit frame."""

from __future__ import annotations

import hashlib
from collections.abc import Sequence

import numpy as np

from pranet.core.confidence import subsample
from pranet.core.pipeline import IcpResult
from pranet.core.se3 import Array

POINT_TO_POINT, POINT_TO_PLANE = "point_to_point", "point_to_plane"
METHODS = (POINT_TO_POINT, POINT_TO_PLANE)
Stage = tuple[str, float]  # (estimation method, max correspondence distance in the unit frame)

DEFAULT_MAX_DISTANCE = 0.1  # unit frame (unit-sphere clouds); why 0.1: docs/DESIGN.md "ICP of PRANet-v2"
# A second pass from the first one's result with the window of the baselines' refinement (training.baselines):
# fewer outlier matches once aligned. On all 1266 pairs of the shipped model's v2 runs: noisy success 87.8 ->
# 89.3 %, partial 11.2 -> 20.6 % (docs/PERFORMANCE.md).
DEFAULT_REFINE_DISTANCE = 0.05


def two_windows(
    method: str, max_distance: float = DEFAULT_MAX_DISTANCE, refine_distance: float = DEFAULT_REFINE_DISTANCE
) -> tuple[Stage, ...]:
    """``method`` within ``max_distance``, then again within ``refine_distance`` from that result."""
    return ((method, max_distance), (method, refine_distance))


# The refinement of PRANet-v2 and of the service: point-to-plane in both windows, then point-to-point in both.
# Point-to-plane slides along the surface and reaches the truth from farther off (a wider basin); with normals
# estimated from noisy points it stops less precisely, so point-to-point finishes. Chosen on the validation
# shapes (seen categories, held out from training; `python scripts/icp_select.py`): service-default success on
# noisy pairs 91.2 -> 93.2 %, partial 36.0 -> 51.0 % against point-to-point alone (docs/DESIGN.md).
DEFAULT_STAGES: tuple[Stage, ...] = two_windows(POINT_TO_PLANE) + two_windows(POINT_TO_POINT)
# The rescue of unconfident results: ICP from the input pose with a wide window (that of the ICP baseline),
# refined afterwards by the pipeline's own ICP.
RESCUE_MAX_DISTANCE = 0.5
NORMAL_RADIUS = 0.4  # unit frame; target normals (point-to-plane): PCA over at most NORMAL_MAX_NN neighbours
NORMAL_MAX_NN = 30
DEFAULT_VOXEL = 0.01  # downsample larger targets before ICP
MAX_POINTS_BEFORE_VOXEL = 20000
# ICP's cost grows with the source's points (one nearest-neighbour query each per iteration); a fixed-seed
# random subset of 5000 is 3x faster on the 40k-point bunny scans and no less accurate (0.57° against 1.04° with
# the 0.01 voxel grid; scripts/scan_check.py). ModelNet40 clouds (<= 1024 points) are not touched.
MAX_SOURCE_POINTS = 5000


def to_o3d(points: Array):  # -> open3d.geometry.PointCloud
    import open3d as o3d

    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
    return pc


def make_icp(stages: Sequence[Stage] = DEFAULT_STAGES, max_iterations: int = 50):  # -> IcpFn
    """An ``IcpFn`` running Open3D's ICP from the agent's estimate, one pass per ``(method, max_distance)``
    stage, each from the previous one's result (``DEFAULT_STAGES``: point-to-plane at 0.1 and 0.05, then
    point-to-point at 0.1 and 0.05). Target normals, when a stage needs them, are estimated once per call."""
    import open3d as o3d

    stages = tuple((str(m), float(d)) for m, d in stages)
    if not stages:
        raise ValueError("ICP needs at least one stage")
    for m, d in stages:
        if m not in METHODS or not d > 0:
            raise ValueError(f"bad ICP stage ({m!r}, {d}): method in {METHODS}, distance > 0")
    reg = o3d.pipelines.registration
    estimations = {
        POINT_TO_POINT: reg.TransformationEstimationPointToPoint(),
        POINT_TO_PLANE: reg.TransformationEstimationPointToPlane(),
    }
    criteria = reg.ICPConvergenceCriteria(max_iteration=max_iterations)
    needs_normals = any(m == POINT_TO_PLANE for m, _ in stages)

    last: list[tuple[bytes, object]] = []  # the last target prepared: (fingerprint, open3d cloud)

    def prepared_target(target: Array):  # -> open3d.geometry.PointCloud, down-sampled, with normals if needed
        # One registration refines against the same target several times (exit checks, rescues); its normals
        # cost 35-45 ms on a 15k-point scan. The fingerprint is the content (shape and bytes), not the object.
        t = np.ascontiguousarray(target, dtype=np.float64)
        key = hashlib.blake2b(t.tobytes(), digest_size=16, person=str(t.shape).encode()[:16]).digest()
        if last and last[0][0] == key:
            return last[0][1]
        tgt = to_o3d(t)
        if len(t) > MAX_POINTS_BEFORE_VOXEL:
            tgt = tgt.voxel_down_sample(DEFAULT_VOXEL)
        if needs_normals:
            tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=NORMAL_RADIUS, max_nn=NORMAL_MAX_NN))
        last[:] = [(key, tgt)]  # one entry; a concurrent caller at worst prepares the same cloud twice
        return tgt

    def icp(source: Array, target: Array, init: Array) -> IcpResult:
        src, tgt = to_o3d(subsample(source, MAX_SOURCE_POINTS, seed=3)), prepared_target(target)
        T = np.asarray(init, dtype=np.float64)
        for method, distance in stages:
            r = reg.registration_icp(src, tgt, distance, T, estimations[method], criteria)
            T = r.transformation
        return IcpResult(np.asarray(T).copy(), float(r.fitness), float(r.inlier_rmse))

    return icp


def make_rescue_icp():  # -> IcpFn
    """The wide-window ICP of the rescue (``core.pipeline.register(rescue_icp=...)``), one pass."""
    return make_icp(((POINT_TO_POINT, RESCUE_MAX_DISTANCE),))
