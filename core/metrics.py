"""Registration metrics, RPMNet protocol (Yew & Lee 2020), as used by the paper's tables.

All take ``T_est`` and ``T_gt`` as ``T_target_source`` (``target ≈ R @ source + t``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import numpy.typing as npt

from pranet.core.se3 import Array, apply_transform, inverse, rotation_angle

SUCCESS_ROTATION_DEG = 1.0
SUCCESS_TRANSLATION = 0.01


def isotropic_errors(T_est: npt.ArrayLike, T_gt: npt.ArrayLike) -> tuple[float, float]:
    """(rotation error in degrees, translation error), both from ``inv(T_gt) @ T_est``."""
    E = inverse(T_gt) @ np.asarray(T_est, dtype=np.float64)
    return float(np.rad2deg(rotation_angle(E[:3, :3]))), float(np.linalg.norm(E[:3, 3]))


def clean_l2(clean_source: npt.ArrayLike, T_est: npt.ArrayLike, T_gt: npt.ArrayLike) -> float:
    """Mean distance between the clean complete source ``(N, 3)`` under ``T_est`` and under ``T_gt``."""
    return float(
        np.linalg.norm(apply_transform(T_est, clean_source) - apply_transform(T_gt, clean_source), axis=1).mean()
    )


def _nn_sq_dist(a: Array, b: Array) -> Array:
    """For each row of ``a: (N, 3)``, the squared distance to its nearest row of ``b: (M, 3)``.

    ``core.nearest.nearest_distances``: scipy's KD-tree when installed (the evaluation computes MCD for
    every method and the Fig. 5 Chamfer curve at every step: brute force was two thirds of its time), else
    chunked numpy brute force.
    """
    from pranet.core.nearest import nearest_distances

    return nearest_distances(a, b) ** 2


def modified_chamfer(
    source: npt.ArrayLike,
    target: npt.ArrayLike,
    clean_source: npt.ArrayLike,
    T_est: npt.ArrayLike,
    T_gt: npt.ArrayLike,
) -> float:
    """RPMNet's modified Chamfer distance (squared distances).

    The observed ``source`` under ``T_est`` against the clean complete source under ``T_gt`` (the
    clean target), plus the observed ``target`` against the clean complete source under ``T_est``.
    """
    clean_source = np.asarray(clean_source, dtype=np.float64)
    src_est = apply_transform(T_est, source)
    clean_target = apply_transform(T_gt, clean_source)
    clean_est = apply_transform(T_est, clean_source)
    return float(
        _nn_sq_dist(src_est, clean_target).mean() + _nn_sq_dist(np.asarray(target, dtype=np.float64), clean_est).mean()
    )


def chamfer(a: npt.ArrayLike, b: npt.ArrayLike) -> float:
    """Symmetric mean nearest-neighbour distance (not squared) between two clouds."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return float(np.sqrt(_nn_sq_dist(a, b)).mean() + np.sqrt(_nn_sq_dist(b, a)).mean()) / 2.0


@dataclass(frozen=True)
class PairMetrics:
    rotation_deg: float
    translation: float
    l2: float
    mcd: float

    @property
    def success(self) -> bool:
        return self.rotation_deg < SUCCESS_ROTATION_DEG and self.translation < SUCCESS_TRANSLATION

    def as_dict(self) -> dict[str, float | bool]:
        return {**asdict(self), "success": self.success}


def evaluate_pair(
    source: npt.ArrayLike,
    target: npt.ArrayLike,
    clean_source: npt.ArrayLike,
    T_est: npt.ArrayLike,
    T_gt: npt.ArrayLike,
) -> PairMetrics:
    rot, trans = isotropic_errors(T_est, T_gt)
    return PairMetrics(
        rotation_deg=rot,
        translation=trans,
        l2=clean_l2(clean_source, T_est, T_gt),
        mcd=modified_chamfer(source, target, clean_source, T_est, T_gt),
    )
