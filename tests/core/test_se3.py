import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pranet.core.se3 import (
    apply_transform,
    axis_angle_to_matrix,
    axis_rotation,
    inverse,
    make_transform,
    rotation_angle,
)


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def test_axis_angle_matches_scipy(rng):
    axes = rng.standard_normal((50, 3))
    angles = rng.uniform(0, np.pi, 50)
    ours = axis_angle_to_matrix(axes, angles)
    unit = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    ref = Rotation.from_rotvec(unit * angles[:, None]).as_matrix()
    np.testing.assert_allclose(ours, ref, atol=1e-12)


def test_rotation_angle_matches_scipy(rng):
    R = Rotation.random(100, random_state=3)
    np.testing.assert_allclose(rotation_angle(R.as_matrix()), R.magnitude(), atol=1e-7)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_axis_rotation_is_right_handed(axis):
    ref = Rotation.from_euler("xyz"[axis], 10, degrees=True).as_matrix()
    np.testing.assert_allclose(axis_rotation(axis, np.deg2rad(10)), ref, atol=1e-12)


def test_apply_and_inverse_convention(rng):
    R = Rotation.random(random_state=1).as_matrix()
    t = rng.standard_normal(3)
    T = make_transform(R, t)
    src = rng.standard_normal((20, 3))
    tgt = apply_transform(T, src)
    np.testing.assert_allclose(tgt, (R @ src.T).T + t)  # target = R @ source + t
    np.testing.assert_allclose(apply_transform(inverse(T), tgt), src, atol=1e-12)
    np.testing.assert_allclose(inverse(T) @ T, np.eye(4), atol=1e-12)
