"""ICP refinement with Open3D (PRANet-v2), in the model's unit frame."""

from __future__ import annotations

import numpy as np

from pranet.core.confidence import subsample
from pranet.core.pipeline import IcpResult
from pranet.core.se3 import Array

DEFAULT_MAX_DISTANCE = 0.1  # unit frame (unit-sphere clouds); why 0.1: docs/DESIGN.md "ICP of PRANet-v2"
# A second pass from the first one's result with the window of the baselines' refinement (training.baselines):
# fewer outlier matches once aligned. On all 1266 pairs of the shipped model's v2 runs: noisy success 87.8 ->
# 89.3 %, partial 11.2 -> 20.6 % (docs/PERFORMANCE.md).
DEFAULT_REFINE_DISTANCE = 0.05
# The rescue of unconfident results: ICP from the input pose with a wide window (that of the ICP baseline),
# refined afterwards by the pipeline's own ICP.
RESCUE_MAX_DISTANCE = 0.5
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


def make_icp(
    max_distance: float = DEFAULT_MAX_DISTANCE,
    max_iterations: int = 50,
    method: str = "point_to_point",
    refine_distance: float | None = DEFAULT_REFINE_DISTANCE,
):  # -> IcpFn
    """An ``IcpFn`` running Open3D's ICP from the agent's estimate: within ``max_distance``, then (unless
    ``refine_distance`` is None) again within ``refine_distance`` from that result."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    estimation = (
        reg.TransformationEstimationPointToPlane()
        if method == "point_to_plane"
        else reg.TransformationEstimationPointToPoint()
    )
    criteria = reg.ICPConvergenceCriteria(max_iteration=max_iterations)

    def icp(source: Array, target: Array, init: Array) -> IcpResult:
        src, tgt = to_o3d(subsample(source, MAX_SOURCE_POINTS, seed=3)), to_o3d(target)
        if len(target) > MAX_POINTS_BEFORE_VOXEL:
            tgt = tgt.voxel_down_sample(DEFAULT_VOXEL)
        if method == "point_to_plane":
            tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * max_distance, max_nn=30))
        r = reg.registration_icp(src, tgt, max_distance, np.asarray(init, dtype=np.float64), estimation, criteria)
        if refine_distance is not None:
            r = reg.registration_icp(src, tgt, refine_distance, r.transformation, estimation, criteria)
        return IcpResult(np.asarray(r.transformation).copy(), float(r.fitness), float(r.inlier_rmse))

    return icp


def make_rescue_icp():  # -> IcpFn
    """The wide-window ICP of the rescue (``core.pipeline.register(rescue_icp=...)``), one pass."""
    return make_icp(max_distance=RESCUE_MAX_DISTANCE, refine_distance=None)
