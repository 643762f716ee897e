import numpy as np
from scipy.spatial.transform import Rotation

from pranet.core.knn import knn_indices
from pranet.core.se3 import apply_transform, make_transform
from pranet.core.twins import TWIN_WEIGHT, neighbour_distances, twin_similarity


def sphere(rng: np.random.Generator, n: int) -> np.ndarray:
    p = rng.normal(size=(n, 3))
    return p / np.linalg.norm(p, axis=1, keepdims=True)


def moved_copy(points: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``points`` turned 70° and shifted, in a random order: ``(copy, order)`` with ``copy[j] = T points[order[j]]``."""
    T = make_transform(Rotation.from_rotvec([0.0, 0.0, np.deg2rad(70.0)]).as_matrix(), np.array([0.3, -0.2, 0.1]))
    order = rng.permutation(len(points))
    return apply_transform(T, points[order]).astype(np.float32), order


def test_every_point_finds_its_twin_in_a_moved_copy_and_nothing_else_scores():
    """A sphere is the hardest case for the features (every turn of it is a copy) and none for twins: each source
    point's best match is the point it became, at full weight, and the other pairs score about 0 (a point and its
    nearest neighbour share their first distance, so a rare pair reaches a fraction of a twin's score)."""
    rng = np.random.default_rng(0)
    src = sphere(rng, 512).astype(np.float32)
    tgt, order = moved_copy(src, rng)
    S = twin_similarity(src, knn_indices(src, 16), tgt, knn_indices(tgt, 16))
    twin_of = np.argsort(order)  # the target index of each source point
    np.testing.assert_array_equal(S.argmax(axis=1), twin_of)
    np.testing.assert_allclose(S[np.arange(512), twin_of], TWIN_WEIGHT, atol=1e-3)
    S[np.arange(512), twin_of] = 0.0
    assert S.sum(axis=1).mean() < 0.01 and (S > 0.1).sum() <= 4


def test_independent_samples_of_one_surface_have_no_twins():
    """Two samplings of the same sphere (as the noisy setting and real scans are): the term is about 0 everywhere,
    so it leaves the trained matching alone."""
    rng = np.random.default_rng(1)
    a, b = sphere(rng, 512).astype(np.float32), sphere(rng, 512).astype(np.float32)
    S = twin_similarity(a, knn_indices(a, 16), b, knn_indices(b, 16))
    assert S.sum(axis=1).mean() < 0.01 and S.max() < 0.5


def test_the_descriptor_does_not_move_with_the_pose():
    rng = np.random.default_rng(2)
    src = sphere(rng, 200)
    tgt, order = moved_copy(src, rng)
    d_src = neighbour_distances(src, knn_indices(src, 16))
    d_tgt = neighbour_distances(tgt, knn_indices(tgt, 16))
    np.testing.assert_allclose(d_tgt, d_src[order], atol=1e-6)
    assert (np.diff(d_src, axis=1) >= 0).all() and (d_src[:, 0] > 0).all()  # ascending, self left out


def test_duplicate_points_give_no_term():
    pts = np.zeros((20, 3), np.float32)
    assert not twin_similarity(pts, knn_indices(pts, 16), pts, knn_indices(pts, 16)).any()
