import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pranet.core.confidence import ConfidenceEstimator, estimate_confidence, nearest_distances, subsample
from pranet.core.se3 import make_transform


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
    assert good.chamfer < bad.chamfer
    assert good.tau == pytest.approx(good.spacing)  # one target spacing


def test_identical_clouds_score_one_and_the_score_is_unit_free():
    rng = np.random.default_rng(3)
    shape = _shape(rng, 800)
    T = make_transform(Rotation.random(random_state=3).as_matrix(), [0.2, -0.1, 0.05])
    moved = shape @ T[:3, :3].T + T[:3, 3]
    c = estimate_confidence(shape, moved, T)
    assert c.score == 1.0 and c.status == "converged"
    # The same problem scaled by 1000 (the service works in the unit frame; here: the ratio is scale-free).
    T_big = make_transform(T[:3, :3], 1000 * T[:3, 3])
    assert estimate_confidence(1000 * shape, 1000 * moved, T_big).score == pytest.approx(c.score)


def test_threshold_sets_the_status():
    rng = np.random.default_rng(4)
    shape = _shape(rng, 500)
    c = ConfidenceEstimator(shape, threshold=1.01).evaluate(shape, np.eye(4))
    assert c.score == 1.0 and c.status == "suspect"


def test_large_clouds_are_subsampled_and_fast():
    rng = np.random.default_rng(5)
    big = _shape(rng, 200_000)
    t0 = time.perf_counter()
    c = estimate_confidence(big, big, np.eye(4), threshold=0.4)
    assert time.perf_counter() - t0 < 5.0  # ~0.05 s on an idle core; generous for a loaded CI machine
    assert c.status == "converged" and c.score > 0.4  # independent subsamples of one surface
