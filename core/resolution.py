"""The data's own resolution: how densely each cloud is sampled, and the scales derived from it.

Every distance a registration of real scans uses (voxel grid, normal radius, feature radius, ICP windows,
inlier distance) is a multiple of one measured number, the **spacing**: the median distance from a point to its
nearest neighbour, the coarser of the two clouds. Nothing is a constant of the training data, so a bunny scanned
at 0.5 mm, an RGB-D fragment at 6 mm and a ModelNet40 shape at 0.05 units are handled alike. The multiples
follow the tuned classical pipelines our users compare us with (voxel = 4 spacings; FPFH at 5 voxels; ICP at 2,
then 1 voxel): docs/DESIGN.md, "Resolution first".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from pranet.core.nearest import PointIndex, subsample
from pranet.core.se3 import Array

SPACING_PROBES = 2000  # points whose nearest neighbour is measured (fixed seed): the median is stable to ~1 %
VOXEL_SPACINGS = 4.0  # voxel = 4 spacings: the grid of the global match and of the coarse ICP
NORMAL_VOXELS = 2.0  # normals from neighbours within 2 voxels (at most NORMAL_MAX_NN)
FEATURE_VOXELS = 5.0  # FPFH radius
NORMAL_MAX_NN = 30
DUPLICATE_NEIGHBOURS = 8  # a point repeated more often than this counts as having no spacing
FLATNESS_PROBES = 500  # points whose neighbourhood's out-of-plane spread is measured (fixed seed)
FLATNESS_NEIGHBOURS = 16
# Clouds whose spacing is at most this fraction of the target's radius are dense (every real scan we have:
# 0.0002-0.0074; ModelNet40's 1024-point shapes: 0.025-0.076). Dense clouds get the polish, the deferral of doubtful
# candidates, the looser ICP tolerance and no restarts after the global match; above it the status threshold starts
# to rise (``core.confidence``).
SPARSE_FROM = 0.01
# Surfaces whose flatness (``flatness``) is at most this are smooth at their resolution: dense range scans of objects
# and outdoor LiDAR (about 0.1 and less), not ModelNet40's samples (0.3-0.9) or RGB-D fragments (about 0.5). There a
# point's normal describes the surface: ICP finishes point-to-plane, the polish runs, the ICP target's normals may
# come from further off (``engine.icp``, ``engine.polish``; docs/DESIGN.md, "ICP at the data's resolution").
SMOOTH_UP_TO = 0.25
# A target is planar as a whole when its points lie within PLANAR_UP_TO spacings (RMS) of one plane, or no further
# from it than PLANAR_OVER_FLATNESS times their local out-of-plane spread (``flatness``: a flat shape under sensor
# noise). A door, a leaf, a flat figure: 7 of ModelNet40's 1266 test shapes, exactly flat (planarity 0.001 and less,
# the next 0.57), and under the noisy setting's jitter 1.13-1.17 times their flatness (every other shape 1.23 and
# more). Its normals all agree, so point-to-plane ICP pins only 3 of the 6 degrees of freedom and slides within the
# plane: from the agent's 0.30° it ended 3.4° off and `converged`. A planar cloud is not smooth
# (``Resolution.smooth``) and its ICP runs point-to-point (``engine.icp``): docs/DESIGN.md, "Flat clouds".
PLANAR_UP_TO = 0.25
PLANAR_OVER_FLATNESS = 1.2


def median_spacing(points: npt.ArrayLike | PointIndex, probes: int = SPACING_PROBES, seed: int = 0) -> float:
    """The median distance from a point of ``points: (N, 3)`` to its nearest other point (0 if all coincide).

    Measured for ``probes`` fixed-seed points against the whole cloud; repeated points (distance 0) are skipped:
    each probe's spacing is the distance to its nearest point elsewhere (among its ``DUPLICATE_NEIGHBOURS``
    nearest), so a cloud with repeated rows still reports its sampling density.
    """
    index = points if isinstance(points, PointIndex) else PointIndex(points)
    probe = subsample(index.points, probes, seed=seed)  # (P, 3)
    # Two neighbours (itself and the next) answer every probe that is not repeated; only the repeated ones ask for
    # more: the same spacing at a third of the query's cost on a registration's critical path.
    d = index.neighbours(probe, 2)[0][:, -1]
    repeated = d <= 0
    if repeated.any():
        more, _ = index.neighbours(probe[repeated], DUPLICATE_NEIGHBOURS)  # (R, k), nearest first
        d[repeated] = np.where(more > 0, more, np.inf).min(axis=1)
    positive = d[np.isfinite(d) & (d > 0)]
    return float(np.median(positive)) if len(positive) else 0.0


def flatness(points: npt.ArrayLike | PointIndex, spacing: float, probes: int = FLATNESS_PROBES, seed: int = 0) -> float:
    """How far the surface is from planar at its own resolution: the median, over ``probes`` fixed-seed points of
    ``points: (N, 3)``, of the out-of-plane standard deviation of their ``FLATNESS_NEIGHBOURS`` nearest neighbours
    (the square root of the neighbourhood covariance's smallest eigenvalue), in spacings.

    About 0.1 on dense range scans of smooth objects and outdoor LiDAR, 0.3-0.9 on ModelNet40's 1024-point samples
    of CAD shapes (sparse against their curvature) and about 0.5 on RGB-D fragments (sensor noise): where it is
    large, a point's estimated normal says little about the surface and point-to-plane ICP cannot finish precisely.
    """
    index = points if isinstance(points, PointIndex) else PointIndex(points)
    p = index.points
    if spacing <= 0 or len(p) < FLATNESS_NEIGHBOURS:
        return float("inf")
    _, nearest = index.neighbours(subsample(p, probes, seed=seed), FLATNESS_NEIGHBOURS)
    neighbourhoods = p[nearest]  # (P, k, 3)
    centred = neighbourhoods - neighbourhoods.mean(axis=1, keepdims=True)
    covariance = np.matmul(centred.transpose(0, 2, 1), centred) / FLATNESS_NEIGHBOURS  # (P, 3, 3)
    return float(np.median(np.sqrt(smallest_eigenvalues(covariance)))) / spacing


def smallest_eigenvalues(covariance: Array) -> Array:
    """The smallest eigenvalue (clipped at 0) of each symmetric ``(P, 3, 3)`` matrix, by the trigonometric solution of
    the characteristic cubic: vectorised, where LAPACK's batched ``eigvalsh`` costs a call per matrix."""
    c = np.asarray(covariance, dtype=np.float64)
    q = np.trace(c, axis1=1, axis2=2) / 3.0
    off = c[:, 0, 1] ** 2 + c[:, 0, 2] ** 2 + c[:, 1, 2] ** 2
    diag = (c[:, 0, 0] - q) ** 2 + (c[:, 1, 1] - q) ** 2 + (c[:, 2, 2] - q) ** 2
    p = np.sqrt((diag + 2.0 * off) / 6.0)
    safe = np.where(p > 0, p, 1.0)
    b = (c - q[:, None, None] * np.eye(3)) / safe[:, None, None]
    phi = np.arccos(np.clip(np.linalg.det(b) / 2.0, -1.0, 1.0)) / 3.0
    smallest = np.where(p > 0, q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0), q)
    return np.maximum(smallest, 0.0)


def planarity(points: npt.ArrayLike | PointIndex, spacing: float, probes: int = SPACING_PROBES, seed: int = 0) -> float:
    """How far ``points: (N, 3)`` are from one plane as a whole: the RMS distance of ``probes`` fixed-seed points to
    their best-fitting plane (the smallest singular value of the centred points over the square root of their
    number), in spacings. 0 on a flat cloud; inf when the spacing is unknown (0)."""
    p = points.points if isinstance(points, PointIndex) else np.asarray(points, dtype=np.float64)
    if spacing <= 0 or len(p) < 3:
        return float("inf")
    probe = subsample(p, probes, seed=seed)
    sv = np.linalg.svd(probe - probe.mean(axis=0), compute_uv=False)
    return float(sv[2] / math.sqrt(len(probe))) / spacing


def cloud_radius(points: npt.ArrayLike) -> float:
    """The largest distance of a point of ``points: (N, 3)`` from their centroid."""
    p = np.asarray(points, dtype=np.float64)
    return float(np.linalg.norm(p - p.mean(axis=0), axis=1).max())


@dataclass(frozen=True)
class Resolution:
    """The scales of one registration, all in the units of the clouds it was measured on."""

    spacing: float  # median nearest-neighbour distance, the coarser of the two clouds
    flatness: float = 0.0  # the target's out-of-plane spread at that spacing, in spacings (unit-free)
    # The spacing as a fraction of the target's radius (unit-free): how densely the object is sampled, which decides
    # the status threshold (``core.confidence``) and what runs on dense clouds (``dense``). inf: not measured,
    # counted as sparse.
    relative_spacing: float = math.inf
    # The target's RMS distance from its best plane, in spacings (unit-free; ``planar``). inf: not measured, counted
    # as not planar.
    planarity: float = math.inf

    @property
    def dense(self) -> bool:
        """Whether the clouds are densely sampled (``relative_spacing`` at most ``SPARSE_FROM``)."""
        return self.relative_spacing <= SPARSE_FROM

    @property
    def planar(self) -> bool:
        """Whether the target lies in one plane: ``planarity`` at most ``PLANAR_UP_TO``, or at most
        ``PLANAR_OVER_FLATNESS`` times the surface's own spread (``flatness``), a plane under noise."""
        limit = max(PLANAR_UP_TO, PLANAR_OVER_FLATNESS * self.flatness)
        return math.isfinite(self.planarity) and self.planarity <= limit

    @property
    def smooth(self) -> bool:
        """Whether the surface is smooth at its resolution (``flatness`` at most ``SMOOTH_UP_TO``) and not one plane:
        a plane's normals all agree, so point-to-plane alignment, which smooth surfaces finish with, would leave it
        free to slide within the plane."""
        return self.flatness <= SMOOTH_UP_TO and not self.planar

    @property
    def voxel(self) -> float:
        return VOXEL_SPACINGS * self.spacing

    @property
    def normal_radius(self) -> float:
        return NORMAL_VOXELS * self.voxel

    @property
    def feature_radius(self) -> float:
        return FEATURE_VOXELS * self.voxel

    def scaled(self, factor: float) -> Resolution:
        """The same resolution in units scaled by ``factor`` (e.g. world -> unit frame)."""
        return Resolution(self.spacing * factor, self.flatness, self.relative_spacing, self.planarity)


def measure_resolution(source: Array | PointIndex, target: Array | PointIndex) -> Resolution:
    """The resolution of a pair: the coarser spacing of ``source: (N, 3)`` and ``target: (M, 3)`` (or their
    indexes, built once per registration), so that every scale resolves both clouds, the target's flatness, the
    spacing relative to the target's radius, and the target's planarity."""
    src = source if isinstance(source, PointIndex) else PointIndex(source)
    tgt = target if isinstance(target, PointIndex) else PointIndex(target)
    spacing = max(median_spacing(src, seed=0), median_spacing(tgt, seed=1))
    return Resolution(
        spacing, flatness(tgt, spacing), spacing / cloud_radius(tgt.points), planarity(tgt, spacing, seed=1)
    )
