import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pranet.core.knn import knn_indices
from pranet.core.metrics import clean_l2, evaluate_pair, isotropic_errors, modified_chamfer
from pranet.core.pipeline import prepare
from pranet.core.preprocess import DegenerateCloudError, check_cloud, fit_normalization
from pranet.core.se3 import apply_transform, make_transform


def test_normalization_round_trip_of_transforms():
    rng = np.random.default_rng(0)
    src = rng.standard_normal((500, 3)) * 40 + [100, -20, 5]
    T = make_transform(Rotation.random(random_state=0).as_matrix(), [12.0, -3.0, 40.0])
    tgt = apply_transform(T, src)
    norm = fit_normalization(src, tgt)
    T_unit = norm.transform_to_unit(T)
    # The unit-frame transform maps unit-frame source onto unit-frame target, and maps back exactly.
    np.testing.assert_allclose(apply_transform(T_unit, norm.to_unit(src)), norm.to_unit(tgt), atol=1e-9)
    np.testing.assert_allclose(norm.transform_to_world(T_unit), T, atol=1e-9)
    assert np.linalg.norm(norm.to_unit(tgt), axis=1).max() == pytest.approx(1.0)


def test_prepare_resamples_seeded_rows_of_the_unit_clouds():
    rng = np.random.default_rng(1)
    a, b = rng.standard_normal((1000, 3)), rng.standard_normal((50, 3))
    p1, p2 = prepare(a, b, 256, np.random.default_rng(3)), prepare(a, b, 256, np.random.default_rng(3))
    assert p1.src_n.shape == (256, 3) and p1.tgt_n.shape == (50, 3)  # the smaller cloud whole, no repeats
    np.testing.assert_array_equal(p1.src_n, p2.src_n)
    np.testing.assert_array_equal(p1.tgt_n, p2.tgt_n)
    # Every resampled row is a row of the unit-frame cloud, each once.
    unit_a = p1.norm.to_unit(a)
    assert all(np.isclose(unit_a, row).all(axis=1).any() for row in p1.src_n)
    assert len(np.unique(p1.src_n, axis=0)) == 256 and len(np.unique(p1.tgt_n, axis=0)) == 50


@pytest.mark.parametrize(
    ("points", "message"),
    [
        (np.zeros((0, 3)), "at least 3"),
        (np.ones((2, 3)), "at least 3"),
        (np.ones((10, 2)), "shape"),
        (np.full((10, 3), np.nan), "NaN"),
        (np.ones((10, 3)), "identical"),
        (np.outer(np.arange(10.0), [1, 2, 3]), "collinear"),
    ],
)
def test_check_cloud_rejects_with_a_reason(points, message):
    with pytest.raises(DegenerateCloudError, match=message):
        check_cloud(points, "source")


def test_check_cloud_accepts_a_flat_cloud():
    """A flat outline's rotation is determined (up to its own symmetry), so a plane is not refused."""
    flat = np.c_[np.random.default_rng(0).random((10, 2)), np.zeros(10)]
    np.testing.assert_array_equal(check_cloud(flat, "source"), flat)


def test_metrics_zero_for_perfect_and_match_definitions():
    rng = np.random.default_rng(2)
    clean = rng.standard_normal((300, 3)) * 0.4
    T = make_transform(Rotation.random(random_state=1).as_matrix(), [0.1, 0.2, -0.3])
    src, tgt = clean[:200], apply_transform(T, clean[100:])
    m = evaluate_pair(src, tgt, clean, T, T)
    assert m.rotation_deg == pytest.approx(0.0, abs=1e-5) and m.translation == pytest.approx(0.0, abs=1e-9)
    assert m.l2 == pytest.approx(0.0, abs=1e-9) and m.mcd == pytest.approx(0.0, abs=1e-9) and m.success
    # A 2° error about z through the origin and a 0.05 offset.
    E = make_transform(Rotation.from_euler("z", 2, degrees=True).as_matrix(), [0.05, 0, 0])
    rot, trans = isotropic_errors(T @ E, T)
    assert rot == pytest.approx(2.0) and trans == pytest.approx(0.05)
    assert clean_l2(clean, T @ E, T) == pytest.approx(np.linalg.norm(apply_transform(E, clean) - clean, axis=1).mean())
    assert modified_chamfer(src, tgt, clean, T @ E, T) > 0
    assert not evaluate_pair(src, tgt, clean, T @ E, T).success


def test_knn_matches_brute_force():
    p = np.random.default_rng(3).random((100, 3)).astype(np.float32)
    idx = knn_indices(p, 8)
    d = np.linalg.norm(p[:, None] - p[None], axis=-1)
    ref = np.argsort(d, axis=1)[:, :8]
    np.testing.assert_allclose(np.take_along_axis(d, idx, 1), np.take_along_axis(d, ref, 1), atol=1e-6)
    assert (idx[:, 0] == np.arange(100)).all()
    # Rigid motion leaves the graph unchanged: the same neighbour sets (float32 rounding may swap the order
    # of two neighbours at almost equal distance, never the set, for points this far apart).
    R = Rotation.random(random_state=2).as_matrix().astype(np.float32)
    moved = knn_indices((p @ R.T + 5.0).astype(np.float32), 8)
    np.testing.assert_array_equal(np.sort(moved, axis=1), np.sort(ref, axis=1))
