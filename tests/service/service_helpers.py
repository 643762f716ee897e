"""Helpers of the service tests (imported by name: pytest puts this folder on sys.path)."""

from __future__ import annotations

import base64
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

# Agent steps for tests that check accuracy: a couple of fine steps exercise the agent without making the
# test depend on how good the shipped model is; ICP then converges from there.
FEW_STEPS = [0, 2]


def synthetic_pair(n: int = 600, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An anisotropic random cloud and its copy moved by a known 5° rotation and small translation.

    Returns ``(source (n, 3), target (n, 3), T_target_source (4, 4))`` with ``target = R @ source + t``,
    all float32-representable (so the list and base64 encodings carry the same numbers).
    """
    rng = np.random.default_rng(seed)
    source = (rng.normal(size=(n, 3)) * [1.0, 0.5, 0.25]).astype(np.float32).astype(np.float64)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.deg2rad(5.0) * np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)).as_matrix()
    T[:3, 3] = [0.05, -0.03, 0.02]
    target = (source @ T[:3, :3].T + T[:3, 3]).astype(np.float32).astype(np.float64)
    return source, target, T


def b64(points: Any) -> dict[str, str]:
    """The compact encoding of ``points (N, 3)``."""
    raw = np.asarray(points, dtype="<f4").tobytes()
    return {"encoding": "base64-float32-le", "data": base64.b64encode(raw).decode()}


def rotation_error_deg(R: Any, R_gt: Any) -> float:
    cos = (np.trace(np.asarray(R_gt).T @ np.asarray(R)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def bumpy_shape(n: int = 512, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` points of an ellipsoid with bumps: no rotational symmetry, so every rotation of it is
    recoverable, and about unit size (the scale the model was trained at)."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = 1 + 0.15 * np.sin(3 * u[:, 0]) * np.cos(2 * u[:, 1]) + 0.1 * np.sin(4 * u[:, 2])
    return (u * r[:, None] * [0.8, 0.55, 0.35]).astype(np.float32).astype(np.float64)


def flat_shape(n: int = 1024, seed: int = 0) -> np.ndarray:
    """``(n, 3)`` points filling a flat outline in the plane z = 0.2 (a 1.2 x 0.5 plate with a disc of radius 0.3
    on one end, off its axis, as a door or a leaf is flat): no symmetry within the plane, so every rotation of
    it is recoverable, while its normals all agree."""
    rng = np.random.default_rng(seed)
    plate = rng.uniform([-0.6, -0.25], [0.6, 0.25], (n, 2))
    angle, radius = rng.uniform(0, 2 * np.pi, n), 0.3 * np.sqrt(rng.uniform(0, 1, n))
    disc = np.c_[0.5 + radius * np.cos(angle), 0.2 + radius * np.sin(angle)]
    xy = np.where(rng.uniform(size=(n, 1)) < 0.6, plate, disc)
    return np.c_[xy, np.full(n, 0.2)].astype(np.float32).astype(np.float64)
