"""Preprocessing of real inputs: one common similarity maps both clouds into the model's unit frame.

``x_unit = scale * (x - center)`` with ``center`` the target centroid and ``scale`` one common
factor that puts both clouds (each about its own centroid) inside the unit sphere, as the training
data is. The relative offset of the clouds is kept, so the agent sees the same kind of state it was
trained on. A transform found in the unit frame maps back to world units exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from pranet.core.se3 import Array, make_transform


class DegenerateCloudError(ValueError):
    """A cloud that cannot be registered: too few points, non-finite values, or no 3-D extent."""


@dataclass(frozen=True)
class Normalization:
    center: Array  # (3,)
    scale: float

    def to_unit(self, points: npt.ArrayLike) -> Array:
        """``(N, 3)`` world -> unit frame."""
        return (np.asarray(points, dtype=np.float64) - self.center) * self.scale

    def transform_to_world(self, T_unit: npt.ArrayLike) -> Array:
        """``T_target_source`` in the unit frame -> the same transform in world units."""
        T_unit = np.asarray(T_unit, dtype=np.float64)
        R, t = T_unit[:3, :3], T_unit[:3, 3]
        return make_transform(R, self.center - R @ self.center + t / self.scale)

    def transform_to_unit(self, T_world: npt.ArrayLike) -> Array:
        T_world = np.asarray(T_world, dtype=np.float64)
        R, t = T_world[:3, :3], T_world[:3, 3]
        return make_transform(R, self.scale * (t - self.center + R @ self.center))


def check_cloud(points: npt.ArrayLike, name: str, min_points: int = 3) -> Array:
    """Return ``points`` as ``(N, 3)`` float64, or raise ``DegenerateCloudError`` saying what is wrong."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise DegenerateCloudError(f"{name}: expected an array of shape (N, 3), got {p.shape}")
    if len(p) < min_points:
        raise DegenerateCloudError(f"{name}: needs at least {min_points} points, got {len(p)}")
    if not np.isfinite(p).all():
        raise DegenerateCloudError(f"{name}: contains NaN or infinite values")
    centered = p - p.mean(axis=0)
    sv = np.linalg.svd(centered[:: max(1, len(p) // 20000)], compute_uv=False)
    if sv[0] <= 1e-12 * max(1.0, np.abs(p).max()):
        raise DegenerateCloudError(f"{name}: all points are identical")
    if sv[1] <= 1e-6 * sv[0]:
        raise DegenerateCloudError(f"{name}: points are collinear; a rotation about their line is undetermined")
    return p


def fit_normalization(source: Array, target: Array) -> Normalization:
    """Centre on the target centroid; one scale so both clouds fit the unit sphere about their centroids."""
    center = target.mean(axis=0)
    radius = max(
        np.linalg.norm(target - center, axis=1).max(),
        np.linalg.norm(source - source.mean(axis=0), axis=1).max(),
    )
    return Normalization(center=center, scale=1.0 / float(radius))


def resample(points: Array, n: int, rng: np.random.Generator) -> Array:
    """``n`` rows of ``points``: without replacement when there are enough, else with."""
    if len(points) == n:
        return points[rng.permutation(n)]
    return points[rng.choice(len(points), n, replace=len(points) < n)]
