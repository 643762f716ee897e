"""The data's own resolution: how densely each cloud is sampled, and the scales derived from it.

Every distance a registration of real scans uses (voxel grid, normal radius, feature radius, ICP windows,
inlier distance) is a multiple of one measured number, the **spacing**: the median distance from a point to its
nearest neighbour, the coarser of the two clouds. Nothing is a constant of the training data, so a bunny scanned
at 0.5 mm, an RGB-D fragment at 6 mm and a ModelNet40 shape at 0.05 units are handled alike. The multiples
follow the tuned classical pipelines our users compare us with (voxel = 4 spacings; FPFH at 5 voxels; ICP at 2,
then 1 voxel): docs/DESIGN.md, "Resolution first".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from pranet.core.nearest import nearest_distances, subsample
from pranet.core.se3 import Array

SPACING_PROBES = 2000  # points whose nearest neighbour is measured (fixed seed): the median is stable to ~1 %
VOXEL_SPACINGS = 4.0  # voxel = 4 spacings: the grid of the global match and of the coarse ICP
NORMAL_VOXELS = 2.0  # normals from neighbours within 2 voxels (at most NORMAL_MAX_NN)
FEATURE_VOXELS = 5.0  # FPFH radius
NORMAL_MAX_NN = 30


def median_spacing(points: npt.ArrayLike, probes: int = SPACING_PROBES, seed: int = 0) -> float:
    """The median distance from a point of ``points: (N, 3)`` to its nearest other point (0 if all coincide).

    Measured for ``probes`` fixed-seed points against the whole cloud; duplicated points (distance 0) are
    skipped, so a cloud with repeated rows still reports its sampling density.
    """
    p = np.asarray(points, dtype=np.float64)
    d = nearest_distances(subsample(p, probes, seed=seed), p, exclude_self=True)
    positive = d[d > 0]
    return float(np.median(positive)) if len(positive) else 0.0


@dataclass(frozen=True)
class Resolution:
    """The scales of one registration, all in the units of the clouds it was measured on."""

    spacing: float  # median nearest-neighbour distance, the coarser of the two clouds

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
        return Resolution(self.spacing * factor)


def measure_resolution(source: Array, target: Array) -> Resolution:
    """The resolution of a pair: the coarser spacing of ``source: (N, 3)`` and ``target: (M, 3)``, so that
    every scale resolves both clouds."""
    return Resolution(max(median_spacing(source, seed=0), median_spacing(target, seed=1)))
