"""The classical global candidates, at the data's own resolution: a ``GlobalMatchFn`` of ``core.pipeline``.

``global_matches`` offers KISS-Matcher's answers (FPFH on a voxel grid, graph-theoretic outlier pruning and a robust
solver) on a grid of two voxels, then of one, then, unless KISS-Matcher's answer rests on enough matches, Open3D's
FPFH + RANSAC at one voxel; lazily, so the pipeline pays only for those it asks for before one is confident.
KISS-Matcher first: as accurate on the real-scan pairs and several times faster, with no random sampling (but its
matching runs on TBB threads, whose order moves its answer a little: docs/DESIGN.md, "Same request, same answer");
RANSAC is seeded with the request's seed and runs on one thread, so it repeats exactly (docs/DESIGN.md, "The global
candidate"). All take the clouds in the unit frame.

KISS-Matcher turns every normal toward the origin of the coordinates it is given (its FPFH needs one consistent
side of the surface), which assumes the origin is where the sensor was. Scans come in their sensor's frame (a
range scanner's, an RGB-D camera's, a LiDAR's), so it runs about ``viewpoint``, the input frame's origin, not about
the unit frame's centre: centred, the two fragments of the 3DMatch demo pair had their normals turned toward two
different points of the room and it found one consistent match (74° off, then 450 ms of RANSAC); about the input
origin, 19 matches and 6° (docs/DESIGN.md, "The global match: where it looks from, on which grid, and when
RANSAC follows").
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from pranet.core.nearest import subsample
from pranet.core.registration_types import GlobalAnswer
from pranet.core.resolution import FEATURE_VOXELS, NORMAL_MAX_NN, Resolution
from pranet.core.se3 import Array, make_transform

# KISS-Matcher refuses voxels below a floor of its own (it is tuned for LiDAR in metres): it works on the clouds
# scaled so that the voxel is 1, and the translation is scaled back.
SCALED_VOXEL = 1.0
# KISS-Matcher's grids, in voxels, coarsest first. Its answer only has to land within the first ICP stage's window
# (8 spacings: 2 voxels), and on a grid of 2 voxels it costs 2-3x less (about 75 against 185 ms on the object scans)
# with the same final answers on all 36 real-scan pairs we have; on 3 voxels it lost 4 of them. The finer grid runs
# only when the coarse answer, refined, is not confident (docs/DESIGN.md, "The global match: where it looks from,
# on which grid, and when RANSAC follows").
KISS_GRIDS = (2.0, 1.0)
# On dense clouds whose surface is smooth at its resolution (``Resolution.dense`` and ``smooth``: where the polish
# runs), KISS-Matcher's input is first averaged on a grid of this many of its voxels (None: never): its own voxel
# grid, normals and features then see a few thousand points, not every point of a dense scan. On the bunny views it
# took 45-50 ms instead of 80-130, and the requests the global match wins 0.76-0.88x as long, with the same answers
# on all 44 real-scan pairs; on noisy RGB-D fragments the averaging moved its features (the requests 1.08-1.34x as
# long), so they keep their points, as do sparse shapes (ModelNet40's), where there is no time to save
# (docs/DESIGN.md, "The ICP's target on one voxel").
KISS_INPUT_GRID: float | None = 0.5
MIN_FINAL_INLIERS = 3  # fewer translation inliers: no answer (three matches fix a rigid motion)
# An answer resting on fewer matches is still offered, but RANSAC (another algorithm, other failures) follows it when
# it is not confident: on the 36 real-scan pairs right answers rest on 16-650 matches and wrong ones on 0-6, as did a
# wrong one, 110° off, on a 256-point synthetic shape that RANSAC then got right; a LiDAR pair's 68-133 spare it
# 2.5 s of RANSAC.
TRUSTED_INLIERS = 10
MAX_POINTS = 100_000  # per cloud, before its own voxel grid (fixed-seed subset): bounds its memory and time
# Open3D's feature RANSAC, as in the tuned classical pipeline users compare us with.
RANSAC_ITERATIONS = 100_000
RANSAC_CONFIDENCE = 0.999
RANSAC_CHECK_VOXELS = 1.5  # inlier distance and distance checker
EDGE_LENGTH_RATIO = 0.9
FPFH_MAX_NN = 100


# Fewer occupied voxels than this in either cloud: too few features to match, and KISS-Matcher 1.0.2 crashes the
# process (a segmentation fault) on clouds of 4-5 voxels; the pipeline keeps its other candidates.
MIN_VOXELS = 30
VOXEL_COUNT_POINTS = 5000  # a fixed-seed subset is enough to tell a handful of voxels from many


def occupied_voxels(points: Array, voxel: float) -> int:
    """How many cells of a grid of size ``voxel`` hold at least one of ``points: (N, 3)``."""
    cells = np.floor(np.asarray(points, dtype=np.float64) / voxel).astype(np.int64)  # (N, 3)
    cells -= cells.min(axis=0)
    extent = cells.max(axis=0) + 1
    # One integer per cell (row-major over the occupied box): np.unique on 1-D keys, not on rows, is 10x faster.
    return len(np.unique((cells[:, 0] * extent[1] + cells[:, 1]) * extent[2] + cells[:, 2]))


def enough_voxels(source: Array, target: Array, voxel: float) -> bool:
    """Whether both clouds cover at least ``MIN_VOXELS`` cells of a grid of size ``voxel`` (counted on fixed-seed
    subsets)."""
    counts = (occupied_voxels(subsample(p, VOXEL_COUNT_POINTS, seed=5), voxel) for p in (source, target))
    return min(counts) >= MIN_VOXELS


def global_matches(
    source: Array, target: Array, resolution: Resolution, seed: int = 0, viewpoint: Array | None = None
) -> Iterator[GlobalAnswer]:
    """Answers (``T_target_source`` (4, 4) and the matches it rests on) of ``source: (N, 3)`` onto
    ``target: (M, 3)`` from any initial pose, cheapest first, each computed when asked for: KISS-Matcher's on each
    of ``KISS_GRIDS``, then RANSAC's unless KISS-Matcher's answer on the finest grid rests on ``TRUSTED_INLIERS``
    matches or more. None at all where the clouds cover fewer than ``MIN_VOXELS`` voxels. ``viewpoint`` (3,): where
    the sensor was, in the clouds' frame (``None``: their origin)."""
    if not enough_voxels(source, target, resolution.voxel):
        return
    inliers = 0
    for grid in KISS_GRIDS:
        T, inliers = kiss_matcher_match(source, target, resolution, seed, viewpoint, grid)
        if T is not None:
            yield GlobalAnswer(T, inliers)
    if inliers < TRUSTED_INLIERS:
        T = ransac_global_match(source, target, resolution, seed)
        if T is not None:
            yield GlobalAnswer(T)


def kiss_matcher_global_match(
    source: Array,
    target: Array,
    resolution: Resolution,
    seed: int = 0,
    viewpoint: Array | None = None,
    grid: float = 1.0,
) -> Array | None:
    """``T_target_source`` (4, 4) of ``source: (N, 3)`` onto ``target: (M, 3)`` from any initial pose, by
    KISS-Matcher on a grid of ``grid`` voxels, in coordinates centred on ``viewpoint`` (``None``: the origin);
    ``None`` when it finds no consistent set of matches or the clouds cover fewer than ``MIN_VOXELS`` cells of that
    grid (it would crash on a handful). ``seed`` picks the subset of clouds over ``MAX_POINTS`` (the solver itself
    is deterministic)."""
    return kiss_matcher_match(source, target, resolution, seed, viewpoint, grid)[0]


def kiss_matcher_match(
    source: Array, target: Array, resolution: Resolution, seed: int, viewpoint: Array | None, grid: float
) -> tuple[Array | None, int]:
    """``kiss_matcher_global_match``'s answer and how many matches it rests on (its final inliers; 0 without one)."""
    import kiss_matcher

    voxel = grid * resolution.voxel
    if not enough_voxels(source, target, voxel):
        return None, 0
    origin = np.zeros(3) if viewpoint is None else np.asarray(viewpoint, dtype=np.float64).reshape(3)
    scale = SCALED_VOXEL / voxel
    config = kiss_matcher.KISSMatcherConfig(SCALED_VOXEL, fpfh_r_gain=FEATURE_VOXELS)
    matcher = kiss_matcher.KISSMatcher(config)
    averaged = KISS_INPUT_GRID if resolution.dense and resolution.smooth else None
    src = _kiss_input((subsample(source, MAX_POINTS, seed=seed) - origin) * scale, averaged)
    tgt = _kiss_input((subsample(target, MAX_POINTS, seed=seed + 1) - origin) * scale, averaged)
    solution = matcher.estimate(src, tgt)
    inliers = int(matcher.get_num_final_inliers()) if solution.valid else 0
    if inliers < MIN_FINAL_INLIERS:
        return None, 0
    # It maps source - origin onto target - origin: target = R @ source + t / scale + origin - R @ origin.
    R = np.asarray(solution.rotation, dtype=np.float64)
    t = np.asarray(solution.translation, dtype=np.float64).ravel() / scale
    return make_transform(R, t + origin - R @ origin), inliers


def _kiss_input(points: Array, grid: float | None):  # -> (K, 3) float32
    """``points: (N, 3)`` in KISS-Matcher's scaled frame (its voxel is 1), averaged on a grid of ``grid`` (``None``:
    as they are)."""
    if grid is not None:
        from pranet.engine.icp import to_o3d

        points = np.asarray(to_o3d(points).voxel_down_sample(grid).points)
    return np.asarray(points, dtype=np.float32)


def ransac_global_match(source: Array, target: Array, resolution: Resolution, seed: int = 0) -> Array | None:
    """Open3D's FPFH + RANSAC (mutual filter off, edge-length and distance checkers) at ``resolution.voxel``."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    voxel = resolution.voxel
    src, src_f = _fpfh(subsample(source, MAX_POINTS, seed=seed), voxel)
    tgt, tgt_f = _fpfh(subsample(target, MAX_POINTS, seed=seed + 1), voxel)
    o3d.utility.random.seed(seed)  # Open3D's RANSAC draws from its one global generator
    distance = RANSAC_CHECK_VOXELS * voxel
    with one_open3d_thread():
        result = reg.registration_ransac_based_on_feature_matching(
            src,
            tgt,
            src_f,
            tgt_f,
            False,
            distance,
            reg.TransformationEstimationPointToPoint(False),
            3,
            [
                reg.CorrespondenceCheckerBasedOnEdgeLength(EDGE_LENGTH_RATIO),
                reg.CorrespondenceCheckerBasedOnDistance(distance),
            ],
            reg.RANSACConvergenceCriteria(RANSAC_ITERATIONS, RANSAC_CONFIDENCE),
        )
    if len(result.correspondence_set) < MIN_FINAL_INLIERS:
        return None
    return np.asarray(result.transformation).copy()


@contextmanager
def one_open3d_thread() -> Iterator[None]:
    """Open3D limited to one thread inside, its limit restored after. Its RANSAC's threads draw their samples from
    the one seeded generator in whatever order they are scheduled, so with several threads the same seed gives
    another answer under another load (Open3D issue #7475; it happened once in CI, 8e-4 apart); with one it is
    repeatable. The cost: 300-600 ms more where RANSAC runs (pairs KISS-Matcher cannot support, 0.45-0.8 s before)."""
    import open3d as o3d

    before = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        yield
    finally:
        o3d.utility.set_max_threads(before)


def _fpfh(points: Array, voxel: float):  # -> (open3d cloud on the voxel grid, its FPFH features)
    import open3d as o3d

    from pranet.engine.icp import to_o3d

    cloud = to_o3d(points).voxel_down_sample(voxel)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_MAX_NN))
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=FEATURE_VOXELS * voxel, max_nn=FPFH_MAX_NN)
    return cloud, o3d.pipelines.registration.compute_fpfh_feature(cloud, search)
