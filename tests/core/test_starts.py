import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pranet.core.se3 import make_transform
from pranet.core.starts import (
    MAX_STARTS,
    geodesic_distances,
    octahedral_group,
    shifted_transforms,
    start_rotations,
    start_transforms,
)


def test_octahedral_group_is_the_24_rotations_of_the_cube():
    g = octahedral_group()
    assert g.shape == (24, 3, 3)
    np.testing.assert_array_equal(g[0], np.eye(3))
    np.testing.assert_allclose(np.einsum("bij,bkj->bik", g, g), np.broadcast_to(np.eye(3), g.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(g), 1.0)
    # closed under composition, all distinct
    products = (g[:, None] @ g[None]).reshape(-1, 9).round(6)
    assert len(np.unique(products, axis=0)) == 24
    assert len(np.unique(g.reshape(-1, 9), axis=0)) == 24


@pytest.mark.parametrize(("n", "covering_deg"), [(24, 63.0), (72, 54.0)])
def test_starts_cover_so3(n, covering_deg):
    """Every rotation is within ``covering_deg`` of a start (the group: 62.8°)."""
    S = start_rotations(n)
    assert S.shape == (n, 3, 3)
    np.testing.assert_array_equal(S[0], np.eye(3))
    probe = Rotation.random(5000, random_state=0).as_matrix()
    assert np.degrees(geodesic_distances(probe, S).min(axis=1).max()) < covering_deg


def test_fewer_starts_are_spread_and_deterministic():
    S = start_rotations(6)
    np.testing.assert_array_equal(S, start_rotations(6))
    d = geodesic_distances(S, S) + np.eye(6) * 10
    assert np.degrees(d.min()) >= 89.9  # 90° apart at least
    with pytest.raises(ValueError):
        start_rotations(0)
    with pytest.raises(ValueError):
        start_rotations(MAX_STARTS + 1)


def test_start_transforms_rotate_about_the_source_centroid_onto_the_target_centroid():
    R = start_rotations(4)
    m, c = np.array([1.0, 2.0, 3.0]), np.array([-0.5, 0.0, 0.5])
    T = start_transforms(R, m, c)
    for Ti, Ri in zip(T, R, strict=True):
        np.testing.assert_allclose(Ti[:3, :3], Ri)
        np.testing.assert_allclose(Ti[:3, :3] @ m + Ti[:3, 3], c)


def test_local_rotations_are_plus_minus_the_angle_about_each_axis():
    from scipy.spatial.transform import Rotation

    from pranet.core.starts import local_rotations

    Q = local_rotations(30.0)
    assert Q.shape == (6, 3, 3)
    expected = [np.deg2rad(30.0) * s * e for e in np.eye(3) for s in (1.0, -1.0)]
    np.testing.assert_allclose(Rotation.from_matrix(Q).as_rotvec(), expected, atol=1e-12)


def test_restart_transforms_turn_the_estimate_about_the_moved_centroid():
    from scipy.spatial.transform import Rotation

    from pranet.core.se3 import make_transform
    from pranet.core.starts import local_rotations, restart_transforms

    T = make_transform(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), np.array([0.4, -0.1, 0.2]))
    m = np.array([0.1, 0.2, -0.3])
    Q = local_rotations(30.0)
    out = restart_transforms(T, m, Q)
    for k in range(6):
        np.testing.assert_allclose(out[k][:3, :3], Q[k] @ T[:3, :3], atol=1e-12)
        np.testing.assert_allclose(out[k][:3, :3] @ m + out[k][:3, 3], T[:3, :3] @ m + T[:3, 3], atol=1e-12)


def test_turned_transforms_keep_or_centre_the_moved_source_centroid():
    """The turns are the well-spread rotations but the identity, applied about where the estimate puts the source
    centroid; the centred ones have the same rotations and put that centroid on the target's."""
    from pranet.core.starts import centred_turned_transforms, turned_transforms

    T = make_transform(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), np.array([0.4, -0.1, 0.2]))
    m, c = np.array([0.1, 0.2, -0.3]), np.array([-0.5, 0.3, 0.05])
    turned, centred = turned_transforms(T, m, 24), centred_turned_transforms(T, m, c, 24)
    Q = start_rotations(24)[1:]
    assert turned.shape == centred.shape == (23, 4, 4)
    for k in range(23):
        np.testing.assert_allclose(turned[k][:3, :3], Q[k] @ T[:3, :3], atol=1e-12)
        np.testing.assert_allclose(centred[k][:3, :3], turned[k][:3, :3], atol=1e-12)
        np.testing.assert_allclose(turned[k][:3, :3] @ m + turned[k][:3, 3], T[:3, :3] @ m + T[:3, 3], atol=1e-12)
        np.testing.assert_allclose(centred[k][:3, :3] @ m + centred[k][:3, 3], c, atol=1e-12)


def test_shifted_transforms_move_the_estimate_along_each_axis_nearest_first():
    T = make_transform(Rotation.from_rotvec([0.2, -0.1, 0.4]).as_matrix(), [1.0, 2.0, 3.0])
    moved = shifted_transforms(T, [0.1, 0.3])  # any distances
    assert moved.shape == (12, 4, 4)
    np.testing.assert_array_equal(moved[:, :3, :3], np.broadcast_to(T[:3, :3], (12, 3, 3)))
    offsets = moved[:, :3, 3] - T[:3, 3]
    np.testing.assert_allclose(np.abs(offsets).sum(axis=1), [0.1] * 6 + [0.3] * 6)
    assert {tuple(np.round(o, 6)) for o in offsets[:6]} == {
        (0.1, 0, 0),
        (-0.1, 0, 0),
        (0, 0.1, 0),
        (0, -0.1, 0),
        (0, 0, 0.1),
        (0, 0, -0.1),
    }
    assert shifted_transforms(T, []).shape == (0, 4, 4)
