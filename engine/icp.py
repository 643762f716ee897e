"""ICP refinement with Open3D (PRANet-v2), in the model's unit frame: ``make_icp(stages)`` -> an ``IcpFn``.

The stages are data of ``core.registration_config``; ``pranet.engine.Engine`` makes one function per config.
Every scale comes from the data's resolution (``core.resolution``), passed in with each call: the windows are
multiples of its spacing (or, for the rescue's wide ICP, fractions of the unit sphere), the target is
voxel-downsampled at one voxel when large, and its normals come from its neighbours within the resolution's
normal radius (on that grid, where the surface is smooth, within 4 of its cells: ``icp_target``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from pranet.core.nearest import subsample
from pranet.core.registration_config import (
    DEFAULT_ICP_STAGES,
    POINT_TO_PLANE,
    POINT_TO_POINT,
    IcpStage,
    check_icp_stages,
)
from pranet.core.registration_types import IcpResult
from pranet.core.resolution import NORMAL_MAX_NN, Resolution
from pranet.core.se3 import Array
from pranet.engine.content_cache import LastByContent
from pranet.engine.polish import polishable

# Point-to-point stages finish the refinement only where the surface is not smooth at the data's resolution
# (``Resolution.smooth``): on ModelNet40's sparse samples a point-to-plane finish cut the service default's success
# from 100 to 86 % (noisy) and 53 to 23 % (partial), while on dense range scans point-to-point's pull towards the
# nearest samples cost precision (bun000 -> bun045: 0.067° after point-to-plane at 2 spacings, 0.107° after the
# point-to-point finish): docs/DESIGN.md, "ICP at the data's resolution".
WINDOW_UNITS = ("spacing", "extent")  # ICP windows in spacings of the data, or in the unit frame (the extent)
# Larger targets are voxel-downsampled at one voxel (4 spacings) before ICP: their normals cost a third (12 against
# 40 ms on a bunny scan, 80 against 300 on a 270k-point RGB-D fragment) and each stage less. The stages mostly rank
# candidates, and the winner of a smooth scan is finished by the polish: the same right and wrong answers on 44
# real-scan pairs, objects as precise to 0.001°, requests 0.6-0.9x as long; the RGB-D fragments' errors moved both
# ways (0.30-0.92° before, 0.45-0.95° after); the LiDAR pair's normals need a wider radius on it (below)
# (docs/DESIGN.md, "The ICP's target on one voxel").
TARGET_VOXEL_SPACINGS = 4.0
MAX_POINTS_BEFORE_VOXEL = 20000
# On that grid, where the surface is smooth at its resolution (``Resolution.smooth``), normals come from the
# neighbours within this many of its cells (16 spacings; at most ``NORMAL_MAX_NN``), as the 2-spacing grid's 8
# spacings spanned 4 of its cells. On a ring LiDAR scan 8 spacings hold a few points of one ring, a line with no
# normal: the LiDAR pair's ICP ended 0.71° / 4.8 cm off on that radius, 0.18° / 2.8 cm on this one (the peers:
# 0.22-0.25° / 2.4-3.3 cm), and the object scans did not move. Noisy surfaces (RGB-D fragments) keep the 8 spacings:
# with 16, ICP slid a cut kitchen fragment 8° along its walls to a pose that scored 0.58, `converged` and wrong
# (docs/DESIGN.md, "The ICP's target on one voxel").
TARGET_NORMAL_CELLS = 4.0
# ICP's cost grows with the source's points (one nearest-neighbour query each per iteration); a fixed-seed random
# subset is faster on large scans and no less accurate than a voxel grid (docs/DESIGN.md, "ICP on real scans").
MAX_SOURCE_POINTS = 2000
# Where the GICP polish finishes the winner (``engine.polish.polishable``: dense, smooth scans) these stages only
# rank the candidates, and half the points rank them as well: the same answers on every object pair of the
# benchmark and its reversed pairs, a quarter off the ICP of a wrong estimate; on RGB-D fragments, which are not
# polished, the finish keeps its 2000 (docs/DESIGN.md, "Fewer ICP points where the polish finishes").
RANKING_SOURCE_POINTS = 1000
# On dense clouds a stage ends once an iteration changes the fitness and the inlier RMSE by less than this relative
# amount, not Open3D's default 1e-6: on an RGB-D fragment every stage otherwise takes all 30 iterations creeping by
# less than the sensor's noise (the 3DMatch demo pair: 170 ms of its ICP), with the same answers on every real-scan
# pair. Sparse clouds keep the default: there a stage costs a few milliseconds, and 1e-4 moved ModelNet40's
# successes both ways (docs/DESIGN.md, "ICP tolerance on dense clouds").
DENSE_TOLERANCE = 1e-4
# With a ``proceed`` question, it is asked after this many iterations of the first stage (docs/DESIGN.md, "The ICP
# gate"); a promising estimate then runs the first stage in full from there.
GATE_ITERATIONS = 10


def to_o3d(points: Array):  # -> open3d.geometry.PointCloud
    import open3d as o3d

    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
    return pc


def icp_target(target: Array, resolution: Resolution, normals: bool = True):  # -> open3d.geometry.PointCloud
    """``target: (M, 3)`` as ICP aligns to it: on a grid of one voxel when over ``MAX_POINTS_BEFORE_VOXEL`` points,
    with normals (when ``normals``) from its neighbours within the resolution's normal radius, or, on that grid where
    the surface is smooth, within ``TARGET_NORMAL_CELLS`` of its cells."""
    import open3d as o3d

    cloud, radius = to_o3d(target), resolution.normal_radius
    if len(target) > MAX_POINTS_BEFORE_VOXEL:
        cell = TARGET_VOXEL_SPACINGS * resolution.spacing
        cloud = cloud.voxel_down_sample(cell)
        if resolution.smooth:
            radius = TARGET_NORMAL_CELLS * cell
    if normals:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=NORMAL_MAX_NN))
    return cloud


def point_to_point_only(stages: Sequence[IcpStage]) -> tuple[IcpStage, ...]:
    """``stages`` with every method point-to-point, a stage that repeats the one before it dropped: a planar target's
    normals all agree and pin only 3 of the 6 degrees of freedom (``Resolution.planar``)."""
    plan: list[IcpStage] = []
    for _, distance in stages:
        stage = (POINT_TO_POINT, distance)
        if not plan or plan[-1] != stage:
            plan.append(stage)
    return tuple(plan)


def make_icp(
    stages: Sequence[IcpStage] = DEFAULT_ICP_STAGES,
    max_iterations: int = 30,
    window_unit: str = "spacing",
    kernel: float | None = None,
):  # -> IcpFn
    """An ``IcpFn`` running Open3D's ICP from an estimate, one pass per ``(method, max_distance)`` stage, each
    from the previous one's result (``DEFAULT_ICP_STAGES``: point-to-plane at 8, 4 and 2 spacings, then
    point-to-point at 2 and 1; the point-to-point stages are skipped where the surface is smooth at its resolution,
    ``Resolution.smooth``, and every stage runs point-to-point where the target is one plane, ``Resolution.planar``).
    ``kernel``: on sparse clouds (not ``Resolution.dense``), the point-to-plane stages weigh
    each match by Tukey's biweight with a scale of this many spacings (``core.registration_config.ICP_KERNEL``);
    ``None``: least squares everywhere.
    ``window_unit``: the stages' distances are in spacings of the data (``"spacing"``) or
    in the unit frame (``"extent"``). The target's preparation (voxel grid, normals) is cached per content."""
    import open3d as o3d

    if window_unit not in WINDOW_UNITS:
        raise ValueError(f"window_unit must be one of {WINDOW_UNITS}, got {window_unit!r}")
    stages = tuple((str(m), float(d)) for m, d in stages)
    if not stages:
        raise ValueError("ICP needs at least one stage")
    if kernel is not None and not kernel > 0:
        raise ValueError(f"kernel must be > 0 or None, got {kernel}")
    check_icp_stages(stages)
    reg = o3d.pipelines.registration
    estimations = {
        POINT_TO_POINT: reg.TransformationEstimationPointToPoint(),
        POINT_TO_PLANE: reg.TransformationEstimationPointToPlane(),
    }
    criteria = reg.ICPConvergenceCriteria(max_iteration=max_iterations)
    dense_criteria = reg.ICPConvergenceCriteria(
        relative_fitness=DENSE_TOLERANCE, relative_rmse=DENSE_TOLERANCE, max_iteration=max_iterations
    )
    gate_criteria = reg.ICPConvergenceCriteria(max_iteration=min(GATE_ITERATIONS, max_iterations))
    needs_normals = any(m == POINT_TO_PLANE for m, _ in stages)

    # One registration refines against the same target several times (exit checks, candidates); its normals cost
    # 35-45 ms on a 15k-point scan.
    targets: LastByContent[object] = LastByContent()  # open3d clouds

    def prepared_target(target: Array, resolution: Resolution):  # -> open3d.geometry.PointCloud
        return targets.get(target, resolution.spacing, lambda t: icp_target(t, resolution, needs_normals))

    def estimation(method: str, resolution: Resolution):  # -> an Open3D TransformationEstimation
        if method == POINT_TO_PLANE and kernel is not None and not resolution.dense:
            return reg.TransformationEstimationPointToPlane(reg.TukeyLoss(kernel * resolution.spacing))
        return estimations[method]

    def stages_for(resolution: Resolution) -> tuple[IcpStage, ...]:
        if resolution.planar:
            return point_to_point_only(stages)
        finish = tuple(s for s in stages if not (resolution.smooth and s[0] == POINT_TO_POINT))
        return finish or stages  # a point-to-point-only list runs as it is

    def icp(
        source: Array,
        target: Array,
        init: Array,
        resolution: Resolution,
        proceed: Callable[[Array], bool] | None = None,
    ) -> IcpResult:
        source_points = RANKING_SOURCE_POINTS if polishable(resolution) else MAX_SOURCE_POINTS
        src, tgt = to_o3d(subsample(source, source_points, seed=3)), prepared_target(target, resolution)
        unit = resolution.spacing if window_unit == "spacing" else 1.0
        T = np.asarray(init, dtype=np.float64)
        plan = stages_for(resolution)
        if proceed is not None:
            # The first stage in two parts, asking after the first: a far-off estimate takes every iteration of the
            # wide stage, and is told hopeless as well after a few (ICP carries nothing from one call to the next
            # but the transform, so the two parts are the one stage).
            method, distance = plan[0]
            r = reg.registration_icp(src, tgt, distance * unit, T, estimation(method, resolution), gate_criteria)
            T = r.transformation
            if not proceed(np.asarray(T)):
                return IcpResult(np.asarray(T).copy(), float(r.fitness), float(r.inlier_rmse))
        stage_criteria = dense_criteria if resolution.dense else criteria
        for method, distance in plan:
            r = reg.registration_icp(src, tgt, distance * unit, T, estimation(method, resolution), stage_criteria)
            T = r.transformation
        return IcpResult(np.asarray(T).copy(), float(r.fitness), float(r.inlier_rmse))

    return icp
