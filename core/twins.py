"""Twin similarity (beyond the paper): which points of two clouds are the same surface point, moved.

Where the two clouds share their points (ModelNet40's clean setting: the target is the source moved; a scan
registered against a moved copy of itself), every source point has a twin in the target whose distances to its
``k`` nearest neighbours are the same numbers, whatever the pose. A turned copy of a near-symmetric shape (a vase
turned about its axis, a box-like night stand by 90°) has no such twins, yet looks the same to the network's
features: 51 of the 63 clean test pairs the agent ended more than 10° off were such turns (docs/DESIGN.md, "The
clean failures are turns about the shape's own axis"). The matching adds ``weight · S`` to its feature similarity,

    S_ij = exp(-|d_i - d_j|² / (2 (σ s)²)),

``d`` a point's sorted neighbour distances, ``s`` the source's median nearest-neighbour distance: 1 for a twin and
about 0 for any other pair, so on independent samples of a surface (noise, partial scans, real data) it is about 0
everywhere and leaves the matching as trained. It depends on neither cloud's pose, so a registration computes it
once. The kNN graphs are the network's own (``core.knn.knn_indices``: sorted, each point first).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from pranet.core.se3 import Array

TWIN_K = 8  # neighbour distances per descriptor
TWIN_SIGMA = 0.05  # the kernel's width, in median nearest-neighbour distances of the source
TWIN_WEIGHT = 1.0  # added to a feature cosine in [-1, 1]: a twin outweighs any feature match


def neighbour_distances(points: npt.ArrayLike, knn: npt.ArrayLike, k: int = TWIN_K) -> Array:
    """``points (N, 3)``, ``knn (N, K)`` (each point first) -> the distances to the ``k`` nearest others ``(N, k)``,
    ascending."""
    p = np.asarray(points, dtype=np.float64)
    idx = np.asarray(knn)[:, 1 : k + 1]
    if idx.shape[1] < k:
        raise ValueError(f"the kNN graph has {np.asarray(knn).shape[1]} columns; a descriptor of {k} needs {k + 1}")
    return np.sort(np.linalg.norm(p[idx] - p[:, None, :], axis=-1), axis=1)


def twin_similarity(
    source: npt.ArrayLike,
    source_knn: npt.ArrayLike,
    target: npt.ArrayLike,
    target_knn: npt.ArrayLike,
    k: int = TWIN_K,
    sigma: float = TWIN_SIGMA,
    weight: float = TWIN_WEIGHT,
) -> np.ndarray:
    """``weight · S`` of the module docstring, ``(N, M)`` float32."""
    ds = neighbour_distances(source, source_knn, k)
    dt = neighbour_distances(target, target_knn, k)
    scale = sigma * float(np.median(ds[:, 0]))
    if not scale > 0:  # duplicate points: no distance to measure a twin by
        return np.zeros((len(ds), len(dt)), dtype=np.float32)
    d2 = (ds * ds).sum(1)[:, None] + (dt * dt).sum(1)[None, :] - 2.0 * ds @ dt.T
    return (weight * np.exp(-np.maximum(d2, 0.0) / (2.0 * scale * scale))).astype(np.float32)
