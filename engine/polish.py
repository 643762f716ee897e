"""The final polish of the winning candidate: small_gicp's GICP (plane-to-plane) at the data's resolution.

Open3D's ICP ranks the candidates (``engine.icp``); the one that wins is refined once more with generalized ICP on
both clouds voxel-downsampled at one voxel (4 spacings), within half a voxel, as the KISS-Matcher + small_gicp
peer finishes (the peer's first pass, within a whole voxel, adds nothing after Open3D's stages: the same medians,
a third of the time). On dense range scans of smooth surfaces this is the more precise finish
(objects of the real-scan pairs, from the truth turned 3°: 0.089° / 0.21 mm against Open3D's stages' 0.10° /
0.34 mm; docs/DESIGN.md, "The polish"). Only on dense clouds (``Resolution.dense``: spacing under
``core.resolution.SPARSE_FROM`` of the target's radius, as the confidence counts sparse) whose surface is smooth
at its resolution (``Resolution.smooth``): on ModelNet40's sparse samples a
voxel grid of 4 spacings leaves a few dozen points (the polish moved an exact clean result 1.5° off) and on noisy
RGB-D fragments a voxel's neighbourhood is no plane.
"""

from __future__ import annotations

import numpy as np

from pranet.core.registration_types import PolishFn
from pranet.core.resolution import Resolution
from pranet.core.se3 import Array
from pranet.engine.content_cache import LastByContent

WINDOWS = (0.5,)  # voxels: Open3D's stages already ended within 2 spacings (half a voxel)
NEIGHBOURS = 10  # small_gicp's default for its covariances
MAX_ITERATIONS = 20


def polishable(resolution: Resolution) -> bool:
    """Whether the polish finishes registrations at ``resolution``: dense clouds (relative spacing at most
    ``Resolution.dense``) whose surface is smooth at its resolution (``Resolution.smooth``)."""
    return resolution.dense and resolution.smooth


def make_polish(threads: int = 1) -> PolishFn:
    """A ``PolishFn``: ``(source, target, T, resolution) -> T`` or ``None`` where the data is not smooth enough.
    The target's voxel grid, covariances and KD-tree are cached per content (one registration polishes once, but
    repeated requests on the same target are common in batch work)."""
    import small_gicp

    targets: LastByContent[tuple] = LastByContent()  # (small_gicp cloud, its KD-tree)

    def prepared(points: Array, voxel: float) -> tuple:
        return targets.get(points, voxel, lambda p: small_gicp.preprocess_points(p, voxel, NEIGHBOURS, threads))

    def polish(source: Array, target: Array, T: Array, resolution: Resolution) -> Array | None:
        if not polishable(resolution):
            return None
        voxel = resolution.voxel
        tgt, tree = prepared(target, voxel)
        src, _ = small_gicp.preprocess_points(np.ascontiguousarray(source, np.float64), voxel, NEIGHBOURS, threads)
        T = np.asarray(T, dtype=np.float64)
        for window in WINDOWS:
            result = small_gicp.align(
                tgt,
                src,
                tree,
                T,
                registration_type="GICP",
                max_correspondence_distance=window * voxel,
                num_threads=threads,
                max_iterations=MAX_ITERATIONS,
                # its default stops at 1e-3 units: in the unit frame, a tenth of a voxel; we want a thousandth
                translation_epsilon=1e-3 * voxel,
            )
            if not result.converged and result.num_inliers == 0:
                return None
            T = np.asarray(result.T_target_source, dtype=np.float64)
        return T.copy()

    return polish
