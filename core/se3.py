"""Small SE(3)/SO(3) helpers on numpy arrays.

Convention: ``T_target_source`` maps source points onto target points, ``target ≈ R @ source + t``.
Points are rows: ``pts: (N, 3)``, so ``apply(T, pts) = pts @ R.T + t``.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]


def make_transform(rotation: npt.ArrayLike, translation: npt.ArrayLike) -> Array:
    """``(3, 3)`` rotation and ``(3,)`` translation -> ``(4, 4)`` homogeneous transform."""
    T = np.eye(4)
    T[:3, :3] = rotation
    T[:3, 3] = translation
    return T


def apply_transform(T: npt.ArrayLike, points: npt.ArrayLike) -> Array:
    """``T: (4, 4)``, ``points: (N, 3)`` -> ``(N, 3)`` = ``points @ R.T + t``."""
    T = np.asarray(T, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


def inverse(T: npt.ArrayLike) -> Array:
    """Inverse of a rigid ``(4, 4)`` transform: ``(R.T, -R.T @ t)``."""
    T = np.asarray(T, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    return make_transform(R.T, -R.T @ t)


def rotation_angle(R: npt.ArrayLike) -> Array:
    """Angle in radians of ``R: ([B,] 3, 3)``: ``arccos((tr R - 1) / 2)`` (paper, "Reward function")."""
    R = np.asarray(R, dtype=np.float64)
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def axis_angle_to_matrix(axis: npt.ArrayLike, angle: npt.ArrayLike) -> Array:
    """Rodrigues' formula. ``axis: ([B,] 3)`` (normalised here), ``angle: ([B])`` radians -> ``([B,] 3, 3)``."""
    axis = np.asarray(axis, dtype=np.float64)
    angle = np.asarray(angle, dtype=np.float64)
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = np.zeros_like(x)
    K = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(axis.shape[:-1] + (3, 3))
    s = np.sin(angle)[..., None, None]
    c = np.cos(angle)[..., None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def axis_rotation(axis_index: int, angle: float) -> Array:
    """Rotation by ``angle`` radians about coordinate axis ``axis_index`` (0=x, 1=y, 2=z)."""
    axis = np.zeros(3)
    axis[axis_index] = 1.0
    return axis_angle_to_matrix(axis, angle)
