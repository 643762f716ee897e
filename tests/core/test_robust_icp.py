"""core.robust_icp: the symmetric robust point-to-point finish, against known transforms."""

import numpy as np
from oracle_scorer import sparse_partial_pair, turned

from pranet.core.metrics import isotropic_errors
from pranet.core.nearest import PointIndex
from pranet.core.robust_icp import symmetric_robust_icp, tukey_weights, weighted_kabsch
from pranet.core.se3 import apply_transform, make_transform


def test_tukey_weights_fall_to_zero_at_the_scale():
    np.testing.assert_allclose(tukey_weights([0.0, 0.5, 1.0, 2.0], 1.0), [1.0, 0.5625, 0.0, 0.0])


def test_weighted_kabsch_recovers_the_transform_and_ignores_zero_weights():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(50, 3))
    T = turned(70.0, [1.0, -2.0, 0.5], [0.3, -0.1, 2.0])
    b = apply_transform(T, a)
    b[:10] += rng.normal(size=(10, 3))  # outliers, weighted out
    w = np.r_[np.zeros(10), np.ones(40)]
    np.testing.assert_allclose(weighted_kabsch(a, b, w), T, atol=1e-10)


def test_weighted_kabsch_returns_a_rotation_not_a_reflection_for_planar_points():
    rng = np.random.default_rng(1)
    a = np.c_[rng.normal(size=(30, 2)), np.zeros(30)]
    b = a * [1.0, -1.0, 1.0]  # the mirror image: the best orthogonal fit is a reflection
    R = weighted_kabsch(a, b, np.ones(30))[:3, :3]
    assert np.linalg.det(R) > 0.999


def test_points_beyond_the_overlap_do_not_pull_the_finish():
    """The source has 100 points more than the target (a part the target lacks, 0.3 beyond its surface): from 3°
    off the finish lands on the truth exactly, as the kernel (0.1) gives those points no weight; one
    least-squares step on the same matches does not."""
    rng = np.random.default_rng(2)
    u = rng.normal(size=(400, 3))
    shape = u / np.linalg.norm(u, axis=1, keepdims=True) * [0.8, 0.5, 0.3]  # an ellipsoid's surface
    extra = rng.uniform([1.1, -0.2, -0.1], [1.4, 0.2, 0.1], (100, 3))  # a block past its tip (x = 0.8)
    source = np.vstack([shape, extra])
    T = turned(25.0, [1.0, 2.0, -1.0], [0.2, -0.1, 0.3])
    target = apply_transform(T, shape)
    start = turned(3.0, [0.3, 1.0, -0.2], [0.02, 0.0, 0.0]) @ T
    assert PointIndex(target).neighbours(apply_transform(T, extra), 1)[0].min() > 0.1
    result = symmetric_robust_icp(PointIndex(source), PointIndex(target), start, 0.1)
    np.testing.assert_allclose(result, T, atol=1e-6)
    d, j = PointIndex(target).neighbours(apply_transform(T, source), 1)
    least_squares = weighted_kabsch(source, target[j[:, 0]], np.ones(len(source)))
    assert isotropic_errors(least_squares, T)[1] > 0.01


def test_the_finish_moves_sparse_partial_pairs_nearer_the_truth():
    """On sparse noisy partial pairs (spacing about 0.045), from the truth turned 3° and shifted 0.02, every result
    is nearer the truth than its start (measured on 10 seeds: 0.1-2.1°, translations under 0.01)."""
    for seed in range(10):
        source, target, T = sparse_partial_pair(seed)
        start = turned(3.0, [0.3, 1.0, -0.2], [0.02, 0.0, 0.0]) @ T
        rot, trans = isotropic_errors(symmetric_robust_icp(PointIndex(source), PointIndex(target), start, 0.07), T)
        assert rot < 2.5 and trans < 0.012, (seed, rot, trans)


def test_no_match_within_the_scale_leaves_the_estimate_as_it_was():
    source, target, T = sparse_partial_pair(0)
    far = make_transform(np.eye(3), [10.0, 0.0, 0.0]) @ T
    np.testing.assert_array_equal(symmetric_robust_icp(PointIndex(source), PointIndex(target), far, 0.1), far)
