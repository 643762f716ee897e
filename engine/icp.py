"""ICP refinement with Open3D (PRANet-v2), in the model's unit frame: ``make_icp(stages)`` -> an ``IcpFn``.

The stages are data of ``core.registration_config``; ``pranet.engine.Engine`` makes one function per config."""

from __future__ import annotations

import hashlib
from collections.abc import Sequence

import numpy as np

from pranet.core.confidence import subsample
from pranet.core.pipeline import IcpResult
from pranet.core.registration_config import (
    DEFAULT_ICP_STAGES,
    POINT_TO_PLANE,
    POINT_TO_POINT,
    IcpStage,
    check_icp_stages,
)
from pranet.core.se3 import Array

NORMAL_RADIUS = 0.4  # unit frame; target normals (point-to-plane): PCA over at most NORMAL_MAX_NN neighbours
NORMAL_MAX_NN = 30
DEFAULT_VOXEL = 0.01  # downsample larger targets before ICP
MAX_POINTS_BEFORE_VOXEL = 20000
# ICP's cost grows with the source's points (one nearest-neighbour query each per iteration); a fixed-seed random
# subset is faster on large scans and no less accurate than a voxel grid (docs/DESIGN.md, "ICP on real scans").
MAX_SOURCE_POINTS = 5000


def to_o3d(points: Array):  # -> open3d.geometry.PointCloud
    import open3d as o3d

    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
    return pc


def make_icp(stages: Sequence[IcpStage] = DEFAULT_ICP_STAGES, max_iterations: int = 50):  # -> IcpFn
    """An ``IcpFn`` running Open3D's ICP from the agent's estimate, one pass per ``(method, max_distance)``
    stage, each from the previous one's result (``DEFAULT_ICP_STAGES``: point-to-plane at 0.1 and 0.05, then
    point-to-point at 0.1 and 0.05). The target's preparation (voxel grid, normals) is cached per content."""
    import open3d as o3d

    stages = tuple((str(m), float(d)) for m, d in stages)
    if not stages:
        raise ValueError("ICP needs at least one stage")
    check_icp_stages(stages)
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
