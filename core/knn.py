"""k-nearest-neighbour graphs in xyz. Rigid motion does not change them, so a registration computes
each cloud's graph once and reuses it at every step."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt


def knn_indices(points: npt.ArrayLike, k: int) -> npt.NDArray[np.int64]:
    """``points: ([B,] N, 3)`` -> ``([B,] N, k)`` indices of the k nearest points (each point first)."""
    p = np.asarray(points, dtype=np.float32)
    sq = (p * p).sum(-1)
    d2 = sq[..., :, None] - 2.0 * p @ np.swapaxes(p, -1, -2) + sq[..., None, :]  # ([B,] N, N)
    n = p.shape[-2]
    k = min(k, n)
    idx = np.argpartition(d2, k - 1, axis=-1)[..., :k]
    order = np.argsort(np.take_along_axis(d2, idx, axis=-1), axis=-1)
    return np.take_along_axis(idx, order, axis=-1).astype(np.int64)
