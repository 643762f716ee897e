import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pranet.core.confidence import INLIER_SPACINGS, Confidence, ConfidenceEstimator, estimate_confidence
from pranet.core.nearest import nearest_distances, subsample
from pranet.core.resolution import measure_resolution
from pranet.core.se3 import apply_transform, make_transform


def _shape(rng, n):
    """An asymmetric surface inside the unit sphere: an ellipsoid with a smaller one stuck to its side."""
    u = rng.standard_normal((n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    big = n * 3 // 4
    p = np.concatenate([u[:big] * [0.9, 0.5, 0.3], u[big:] * [0.2, 0.2, 0.3] + [0.4, 0.5, 0.1]])
    return p / np.linalg.norm(p, axis=1).max()


@pytest.mark.parametrize("scipy_tree", [True, False], ids=["kd-tree", "numpy brute force"])
def test_nearest_distances_match_all_pairs_distances(scipy_tree, monkeypatch):
    """Both paths (scipy's KD-tree, the numpy fallback without scipy) against the full distance matrix."""
    from scipy.spatial.distance import cdist

    if not scipy_tree:
        import builtins

        real_import = builtins.__import__

        def no_scipy(name, *args, **kwargs):
            if name.startswith("scipy"):
                raise ImportError(name)
            return real_import(name, *args, **kwargs)

        monkeypatch.setattr(builtins, "__import__", no_scipy)
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal((700, 3)), rng.standard_normal((900, 3))
    full_ab, full_bb = cdist(a, b), cdist(b, b)
    np.testing.assert_allclose(nearest_distances(a, b, chunk=128), full_ab.min(1), atol=1e-6)
    # exclude_self: a point's distance to itself does not count
    np.fill_diagonal(full_bb, np.inf)
    np.testing.assert_allclose(nearest_distances(b, b, exclude_self=True), full_bb.min(1), atol=1e-6)


def test_subsample_is_a_fixed_subset():
    p = np.random.default_rng(1).standard_normal((5000, 3))
    s = subsample(p, 100)
    assert s.shape == (100, 3)
    np.testing.assert_array_equal(s, subsample(p, 100))
    assert subsample(p[:50], 100).shape == (50, 3)


def test_aligned_scores_high_and_misaligned_low():
    """Two independent noisy samples of one shape: aligned -> converged, 30° off -> suspect."""
    rng = np.random.default_rng(2)
    shape = _shape(rng, 4000)
    src = shape[rng.choice(4000, 1000, replace=False)] + rng.normal(0, 0.005, (1000, 3))
    tgt = shape[rng.choice(4000, 1000, replace=False)] + rng.normal(0, 0.005, (1000, 3))
    good = estimate_confidence(src, tgt, np.eye(4))
    R = Rotation.from_rotvec(np.deg2rad(30) * np.array([0.0, 0.6, 0.8])).as_matrix()
    bad = estimate_confidence(src, tgt, make_transform(R, [0.0, 0.0, 0.0]))
    assert 0.0 <= bad.score < good.score <= 1.0
    assert good.status == "converged" and bad.status == "suspect", (good, bad)
    assert good.tau == pytest.approx(INLIER_SPACINGS * good.spacing)  # a multiple of the data's spacing
    assert good.spacing == pytest.approx(measure_resolution(src, tgt).spacing)


def _crop(points, lo, hi):
    """The points whose x lies in [lo, hi): a partial scan of the shape."""
    return points[(points[:, 0] >= lo) & (points[:, 0] < hi)]


def test_a_right_partial_result_is_converged_and_a_wrong_one_suspect():
    """Two crops of one surface that overlap in about a third of each: at the truth the score is as high as for
    complete clouds (the overlap region is tight), while the fraction of the source that lands on the target is
    only the overlap. Shifted by two voxels, or turned by 20°, the result is suspect."""
    rng = np.random.default_rng(6)
    shape = _shape(rng, 20000)
    src = _crop(shape[rng.choice(20000, 8000, replace=False)], -1.0, 0.25)
    tgt = _crop(shape[rng.choice(20000, 8000, replace=False)], -0.25, 1.0)
    T = make_transform(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), [0.1, 0.2, -0.1])
    moved_tgt = apply_transform(T, tgt)
    right = estimate_confidence(src, moved_tgt, T)
    full = estimate_confidence(shape[:8000], apply_transform(T, shape[8000:16000]), T)
    assert right.status == "converged" and right.score > 0.7 * full.score, (right, full)
    assert right.inlier_ratio < 0.6  # the old confidence (this fraction) would call it suspect
    resolution = measure_resolution(src, moved_tgt)
    shifted = T.copy()
    shifted[:3, 3] += [2 * resolution.voxel, 0.0, 0.0]
    turned = T @ make_transform(Rotation.from_rotvec([0.0, 0.0, np.deg2rad(20)]).as_matrix(), np.zeros(3))
    for wrong in (shifted, turned):
        c = estimate_confidence(src, moved_tgt, wrong)
        assert c.status == "suspect" and c.score < right.score - 0.15, c


def test_a_tiny_chance_overlap_is_no_evidence():
    """Clouds that touch only at a few points: even if those points lie tight, the score stays low."""
    rng = np.random.default_rng(7)
    shape = _shape(rng, 8000)
    far = shape + [1.8, 0.0, 0.0]  # the same shape beside the first: their tips nearly touch
    c = estimate_confidence(shape, far, np.eye(4))
    assert c.overlap < 0.1 and c.score < 0.5 and c.status == "suspect", c


def test_identical_clouds_score_one_and_the_score_is_unit_free():
    rng = np.random.default_rng(3)
    shape = _shape(rng, 800)
    T = make_transform(Rotation.random(random_state=3).as_matrix(), [0.2, -0.1, 0.05])
    moved = shape @ T[:3, :3].T + T[:3, 3]
    c = estimate_confidence(shape, moved, T)
    assert c.score == 1.0 and c.status == "converged"
    # The same problem scaled by 1000: every distance is a multiple of the measured spacing.
    T_big = make_transform(T[:3, :3], 1000 * T[:3, 3])
    assert estimate_confidence(1000 * shape, 1000 * moved, T_big).score == pytest.approx(c.score)


def test_threshold_sets_the_status():
    rng = np.random.default_rng(4)
    shape = _shape(rng, 500)
    c = ConfidenceEstimator(shape, shape, measure_resolution(shape, shape), threshold=1.01).evaluate(np.eye(4))
    assert c.score == 1.0 and c.status == "suspect"


def test_large_clouds_cost_a_bounded_number_of_queries():
    rng = np.random.default_rng(5)
    big = _shape(rng, 200_000)
    estimator = ConfidenceEstimator(big, big, measure_resolution(big, big))
    t0 = time.perf_counter()
    c = estimator.evaluate(np.eye(4))
    assert time.perf_counter() - t0 < 1.0  # 2048 queries per direction: ~5 ms on an idle core
    assert c.status == "converged" and c.score == 1.0


@pytest.mark.parametrize("scipy_tree", [True, False], ids=["kd-tree", "numpy brute force"])
def test_the_point_index_agrees_with_all_pairs_distances(scipy_tree, monkeypatch):
    """PointIndex (the confidence's and the resolution's one index per cloud) against all-pairs distances, with
    scipy's KD-tree and with the numpy fallback; beyond ``bound`` a distance may be inf, never wrong."""
    import builtins

    from pranet.core.nearest import PointIndex

    if not scipy_tree:
        real_import = builtins.__import__

        def no_scipy(name, *args, **kwargs):
            if name.startswith("scipy"):
                raise ImportError(name)
            return real_import(name, *args, **kwargs)

        monkeypatch.setattr(builtins, "__import__", no_scipy)
    rng = np.random.default_rng(8)
    points, queries = rng.normal(size=(700, 3)), rng.normal(size=(300, 3)) * 2
    full = np.linalg.norm(queries[:, None] - points[None], axis=2)  # (300, 700)
    index = PointIndex(points)
    d, idx = index.neighbours(queries, 5)
    np.testing.assert_allclose(d, np.sort(full, axis=1)[:, :5], atol=1e-9)
    np.testing.assert_allclose(np.take_along_axis(full, idx, axis=1), d, atol=1e-9)
    bounded = index.nearest(queries, bound=0.5)
    near = full.min(1) <= 0.5
    np.testing.assert_allclose(bounded[near], full.min(1)[near], atol=1e-9)
    assert np.all((bounded[~near] > 0.5) | np.isinf(bounded[~near]))


def test_sparse_clouds_need_a_higher_score_to_be_converged():
    """The bar rises with the spacing relative to the clouds' radius: dense scans keep the base threshold, sparse
    shapes (ModelNet40's 1024 points: 2.5-8 % of the radius) get SPARSE_THRESHOLD, in between it is linear."""
    from pranet.core.confidence import (
        DEFAULT_THRESHOLD,
        SPARSE_AT,
        SPARSE_FROM,
        SPARSE_THRESHOLD,
        status_threshold,
    )
    from pranet.core.resolution import cloud_radius

    assert status_threshold(DEFAULT_THRESHOLD, 0.004) == DEFAULT_THRESHOLD
    assert status_threshold(DEFAULT_THRESHOLD, 0.05) == SPARSE_THRESHOLD
    middle = status_threshold(DEFAULT_THRESHOLD, (SPARSE_FROM + SPARSE_AT) / 2)
    assert middle == pytest.approx((DEFAULT_THRESHOLD + SPARSE_THRESHOLD) / 2)
    assert status_threshold(0.9, 0.05) == 0.9  # never below the base asked for
    rng = np.random.default_rng(9)
    dense, sparse = _shape(rng, 20000), _shape(rng, 300)
    assert 0.9 < cloud_radius(dense) < 1.3  # _shape lies in the unit sphere about the origin, not its centroid
    e_dense = ConfidenceEstimator(dense, dense, measure_resolution(dense, dense))
    e_sparse = ConfidenceEstimator(sparse, sparse, measure_resolution(sparse, sparse))
    assert e_dense.threshold == DEFAULT_THRESHOLD and e_sparse.threshold == SPARSE_THRESHOLD


def test_enough_feature_matches_that_icp_kept_certify_a_global_answer():
    """``certify``: a global answer resting on ``CERTIFYING_MATCHES`` matches, which its refinement moved by at most
    ``CERTIFIED_SHIFT_VOXELS`` and ``CERTIFIED_TURN_DEG``, is ``converged`` whatever its score, on dense clouds; one
    match fewer, a larger move, or sparse clouds leave the status to the score."""
    from dataclasses import replace

    from pranet.core.confidence import CERTIFIED_SHIFT_VOXELS, CERTIFIED_TURN_DEG, CERTIFYING_MATCHES, certify

    rng = np.random.default_rng(0)
    p = _shape(rng, 3000)
    low = replace(estimate_confidence(p, p, np.eye(4)), score=0.1, status="suspect")
    n = CERTIFYING_MATCHES
    sure = certify(low, n, CERTIFIED_SHIFT_VOXELS, CERTIFIED_TURN_DEG, dense=True)
    assert sure.status == "converged" and sure.matches == n and sure.score == 0.1
    for args in (
        (n - 1, 0.0, 0.0, True),
        (n, 1.01 * CERTIFIED_SHIFT_VOXELS, 0.0, True),
        (n, 0.0, 1.01 * CERTIFIED_TURN_DEG, True),
        (10 * n, 0.0, 0.0, False),
    ):
        assert certify(low, *args) == low, args


def _confidence(score: float, status: str, matches: int = 0) -> Confidence:
    return Confidence(score, status, score, 1.0, score, score, 0.01, 0.01, matches)


def test_a_certificate_outranks_a_higher_score_but_not_the_status():
    """Converged above suspect; among converged results, one certified by feature matches above a higher-scoring
    one judged by its score alone (a scene can fool the score); otherwise the higher score."""
    certified = _confidence(0.51, "converged", matches=63)
    tighter = _confidence(0.56, "converged")
    assert certified.outranks(tighter) and not tighter.outranks(certified)
    assert _confidence(0.6, "converged", matches=30).outranks(certified)
    assert not _confidence(0.39, "suspect").outranks(_confidence(0.2, "converged", matches=30))
    assert tighter.outranks(_confidence(0.45, "converged")) and not _confidence(0.45, "converged").outranks(tighter)
    assert not tighter.outranks(tighter)
