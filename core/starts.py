"""Start poses of the global mode: a fixed, well-spread set of rotations the agent starts from.

The model was trained on rotations up to 60°, so an arbitrary initial rotation needs a start within
reach of the answer. The 24 rotations of the octahedral group (the cube's symmetries) put every
rotation within 62.8° of one of them; fewer starts are a farthest-point subset of the group (from the
identity), more add farthest points of a fixed-seed Haar sample. The set is a pure function of ``n``.
"""

from __future__ import annotations

import itertools
from functools import lru_cache

import numpy as np
import numpy.typing as npt

from pranet.core.sampling import sample_isotropic_rotations
from pranet.core.se3 import Array, make_transform

OCTAHEDRAL_ORDER = 24
DEFAULT_STARTS = 24
MAX_STARTS = 120
_POOL = 4096  # Haar samples the starts beyond 24 are chosen from
_POOL_SEED = 20220228


def octahedral_group() -> Array:
    """``(24, 3, 3)``: the signed permutation matrices with determinant +1, the identity first."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[range(3), perm] = signs
            if np.linalg.det(R) > 0:
                out.append(R)
    return np.stack(out)


def geodesic_distances(R: Array, Q: Array) -> Array:
    """``R: (A, 3, 3)``, ``Q: (B, 3, 3)`` -> ``(A, B)`` rotation angles of ``R_a^T Q_b`` (radians)."""
    trace = np.einsum("aij,bij->ab", R, Q)  # tr(R^T Q) = sum_ij R_ij Q_ij
    return np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0))


def _farthest_points(pool: Array, chosen: list[int], n: int) -> list[int]:
    d = geodesic_distances(pool, pool[chosen]).min(axis=1)  # (P,)
    while len(chosen) < n:
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, geodesic_distances(pool, pool[i : i + 1])[:, 0])
    return chosen


@lru_cache(maxsize=16)
def _start_rotations(n: int) -> Array:
    group = octahedral_group()
    if n == OCTAHEDRAL_ORDER:
        return group
    if n < OCTAHEDRAL_ORDER:
        return group[_farthest_points(group, [0], n)]
    pool = np.concatenate([group, sample_isotropic_rotations(np.random.default_rng(_POOL_SEED), np.pi, _POOL)])
    return pool[_farthest_points(pool, list(range(OCTAHEDRAL_ORDER)), n)]


def start_rotations(n: int = DEFAULT_STARTS) -> Array:
    """``(n, 3, 3)`` well-spread rotations, the identity first; ``1 <= n <= MAX_STARTS``."""
    if not 1 <= n <= MAX_STARTS:
        raise ValueError(f"the number of starts must be in [1, {MAX_STARTS}], got {n}")
    return _start_rotations(int(n)).copy()


def start_transforms(rotations: npt.ArrayLike, source_centroid: npt.ArrayLike, target_centroid: npt.ArrayLike) -> Array:
    """``(B, 4, 4)`` ``T_target_source`` starts: rotate the source about its centroid by each of
    ``rotations: (B, 3, 3)`` and move that centroid onto the target's."""
    m = np.asarray(source_centroid, dtype=np.float64)
    c = np.asarray(target_centroid, dtype=np.float64)
    return np.stack([make_transform(Q, c - Q @ m) for Q in np.asarray(rotations, dtype=np.float64)])


RESCUE_ANGLE_DEG = 30.0  # half the training range: a start this far off the estimate stays in the model's reach


def local_rotations(angle_deg: float = RESCUE_ANGLE_DEG) -> Array:
    """``(6, 3, 3)``: rotations by ``±angle_deg`` about x, y and z (the rescue's restarts around an estimate)."""
    a = np.deg2rad(angle_deg)
    out = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            c, s = np.cos(a), sign * np.sin(a)
            i, j = [(1, 2), (2, 0), (0, 1)][axis]
            Q = np.eye(3)
            Q[i, i], Q[i, j], Q[j, i], Q[j, j] = c, -s, s, c
            out.append(Q)
    return np.stack(out)


def restart_transforms(T: npt.ArrayLike, source_centroid: npt.ArrayLike, rotations: npt.ArrayLike) -> Array:
    """``(B, 4, 4)``: the estimate ``T`` (``T_target_source``) turned by each of ``rotations: (B, 3, 3)`` about
    where it puts the source centroid."""
    T = np.asarray(T, dtype=np.float64)
    m = np.asarray(source_centroid, dtype=np.float64)
    c = T[:3, :3] @ m + T[:3, 3]
    return np.stack([make_transform(Q @ T[:3, :3], c - Q @ T[:3, :3] @ m) for Q in np.asarray(rotations)])


def turned_transforms(T: npt.ArrayLike, source_centroid: npt.ArrayLike, n: int) -> Array:
    """``(n - 1, 4, 4)``: the estimate ``T`` turned about where it puts the source centroid by each of the ``n``
    well-spread rotations of ``start_rotations`` but the first (the identity)."""
    return restart_transforms(T, source_centroid, start_rotations(n)[1:])


def centred_turned_transforms(
    T: npt.ArrayLike, source_centroid: npt.ArrayLike, target_centroid: npt.ArrayLike, n: int
) -> Array:
    """``(n - 1, 4, 4)``: the rotations of ``turned_transforms``, each placed as ``start_transforms`` places a start,
    the source centroid on ``target_centroid`` (where a partial answer's translation is off as well as its rotation)."""
    R = np.asarray(T, dtype=np.float64)[:3, :3]
    return start_transforms(start_rotations(n)[1:] @ R, source_centroid, target_centroid)


def shifted_transforms(T: npt.ArrayLike, distances: npt.ArrayLike) -> Array:
    """``(6 D, 4, 4)``: the estimate ``T`` (``T_target_source``) moved by ``±d`` along x, y and z for each of
    ``distances: (D,)`` (the frame's units), nearest first."""
    T = np.asarray(T, dtype=np.float64)
    out = []
    for d in np.asarray(distances, dtype=np.float64):
        for axis in range(3):
            for sign in (1.0, -1.0):
                moved = T.copy()
                moved[axis, 3] += sign * d
                out.append(moved)
    return np.stack(out) if out else np.zeros((0, 4, 4))
