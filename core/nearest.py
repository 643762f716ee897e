"""Nearest neighbours between point sets (numpy; scipy's KD-tree when installed), and fixed-seed subsets."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from pranet.core.se3 import Array

CHUNK = 256  # rows per brute-force block: (256, 4096) float64 distances = 8 MB


def subsample(points: npt.ArrayLike, n_max: int, seed: int = 0) -> Array:
    """At most ``n_max`` rows of ``points: (N, 3)``, chosen by a fixed-seed generator (a pure function)."""
    p = np.asarray(points, dtype=np.float64)
    if len(p) <= n_max:
        return p
    return p[np.sort(np.random.default_rng(seed).choice(len(p), n_max, replace=False))]


def nearest_distances(a: Array, b: Array, chunk: int = CHUNK, exclude_self: bool = False) -> Array:
    """For each row of ``a: (N, 3)``, the distance to its nearest row of ``b: (M, 3)``.

    ``exclude_self``: ``a`` is a subset of ``b`` and a point's zero distance to itself does not count
    (the second smallest distance is taken). With scipy (the service's dependencies have it) a KD-tree
    answers: 1024 x 4096 points in about 2 ms instead of 40 ms by brute force (chunked numpy, the fallback).
    """
    try:
        from scipy.spatial import cKDTree
    except ImportError:  # numpy alone: exact brute force
        return _nearest_brute_force(a, b, chunk, exclude_self)
    k = 2 if exclude_self else 1
    d, _ = cKDTree(b).query(a, k=k)
    return np.asarray(d[:, 1] if exclude_self else d, dtype=np.float64)


def _nearest_brute_force(a: Array, b: Array, chunk: int = CHUNK, exclude_self: bool = False) -> Array:
    out = np.empty(len(a))
    bb = (b * b).sum(1)  # (M,)
    k = 1 if exclude_self else 0
    for i in range(0, len(a), chunk):
        x = a[i : i + chunk]  # (c, 3)
        d2 = (x * x).sum(1)[:, None] - 2.0 * x @ b.T + bb[None]  # (c, M)
        out[i : i + chunk] = np.partition(d2, k, axis=1)[:, k] if k else d2.min(1)
    return np.sqrt(np.maximum(out, 0.0))


def nearest_neighbours(a: Array, b: Array, k: int, chunk: int = CHUNK) -> npt.NDArray[np.int64]:
    """For each row of ``a: (N, 3)``, the indices of its ``k`` nearest rows of ``b: (M, 3)``, nearest first:
    ``(N, k)``. scipy's KD-tree when installed, else chunked brute force."""
    k = min(k, len(b))
    try:
        from scipy.spatial import cKDTree
    except ImportError:
        out = np.empty((len(a), k), dtype=np.int64)
        bb = (b * b).sum(1)
        for i in range(0, len(a), chunk):
            x = a[i : i + chunk]
            d2 = (x * x).sum(1)[:, None] - 2.0 * x @ b.T + bb[None]  # (c, M)
            part = np.argpartition(d2, k - 1, axis=1)[:, :k]
            order = np.argsort(np.take_along_axis(d2, part, axis=1), axis=1)
            out[i : i + chunk] = np.take_along_axis(part, order, axis=1)
        return out
    _, idx = cKDTree(b).query(a, k=k)
    return np.asarray(idx, dtype=np.int64).reshape(len(a), k)
