"""Random rigid transforms (paper, "Sampling Rotations from the SO(3) Manifold").

Isotropic: a uniform axis on the sphere and an angle with the Haar density of SO(3) restricted to
``[0, max_angle]``: ``p(θ) ∝ 1 - cos θ`` (Kuffner 2004). Naive: Euler angles uniform per axis,
for the ablation. Every function takes an explicit ``np.random.Generator``.
"""

from __future__ import annotations

import numpy as np

from pranet.core.se3 import Array, axis_angle_to_matrix

_GRID = 4097


def sample_haar_angle(rng: np.random.Generator, max_angle: float, size: int) -> Array:
    """Angles in ``[0, max_angle]`` radians with density ``∝ 1 - cos θ`` (inverse CDF).

    CDF: ``F(θ) = (θ - sin θ) / (M - sin M)``, inverted by interpolation on a fine grid.
    """
    if not 0.0 <= max_angle <= np.pi:
        raise ValueError(f"max_angle must be in [0, pi], got {max_angle}")
    if max_angle == 0.0:
        return np.zeros(size)
    theta = np.linspace(0.0, max_angle, _GRID)
    cdf = theta - np.sin(theta)
    cdf /= cdf[-1]
    return np.interp(rng.random(size), cdf, theta)


def sample_unit_vectors(rng: np.random.Generator, size: int) -> Array:
    """``(size, 3)`` directions uniform on the unit sphere."""
    v = rng.standard_normal((size, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def sample_isotropic_rotations(rng: np.random.Generator, max_angle: float, size: int) -> Array:
    """``(size, 3, 3)`` rotations, uniform (Haar) on SO(3) restricted to angles ``≤ max_angle`` (radians)."""
    return axis_angle_to_matrix(sample_unit_vectors(rng, size), sample_haar_angle(rng, max_angle, size))


def euler_to_matrix(angles: Array) -> Array:
    """``angles: (B, 3)`` (x, y, z) radians -> ``(B, 3, 3)`` = ``Rz @ Ry @ Rx``."""
    ax, ay, az = angles[:, 0], angles[:, 1], angles[:, 2]
    eye = np.eye(3)
    Rx = axis_angle_to_matrix(np.broadcast_to(eye[0], angles.shape), ax)
    Ry = axis_angle_to_matrix(np.broadcast_to(eye[1], angles.shape), ay)
    Rz = axis_angle_to_matrix(np.broadcast_to(eye[2], angles.shape), az)
    return Rz @ Ry @ Rx


def sample_naive_rotations(rng: np.random.Generator, max_angle_per_axis: float, size: int) -> Array:
    """``(size, 3, 3)``: Euler angles uniform in ``[-m, m]`` per axis (the biased sampling of DCP/RPMNet)."""
    return euler_to_matrix(rng.uniform(-max_angle_per_axis, max_angle_per_axis, (size, 3)))


def sample_rotations(rng: np.random.Generator, method: str, max_angle: float, size: int) -> Array:
    """``method``: ``"isotropic"`` (``max_angle`` is the total angle) or ``"naive"`` (per Euler axis)."""
    if method == "isotropic":
        return sample_isotropic_rotations(rng, max_angle, size)
    if method == "naive":
        return sample_naive_rotations(rng, max_angle, size)
    raise ValueError(f"unknown rotation sampling {method!r}")


def sample_translations(rng: np.random.Generator, max_abs: float, size: int) -> Array:
    """``(size, 3)`` uniform in ``[-max_abs, max_abs]^3``."""
    return rng.uniform(-max_abs, max_abs, (size, 3))
