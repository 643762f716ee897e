"""engine.polish: small_gicp's GICP as the winner's last refinement, only where the surface is smooth."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip("small_gicp")

from pranet.core.metrics import isotropic_errors  # noqa: E402
from pranet.core.nearest import PointIndex  # noqa: E402
from pranet.core.resolution import SMOOTH_UP_TO, measure_resolution  # noqa: E402
from pranet.engine.polish import make_polish  # noqa: E402


def dense_pair(seed: int = 0):
    """A dense, smooth, asymmetric surface (a bumpy ellipsoid, 20k points) and its moved copy, resampled."""
    rng = np.random.default_rng(seed)

    def sample(n):
        u = rng.standard_normal((n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        bump = 1.0 + 0.15 * np.exp(-8 * np.sum((u - [0.6, 0.5, 0.6]) ** 2, axis=1))
        return u * bump[:, None] * [0.9, 0.6, 0.4]

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    T[:3, 3] = [0.05, -0.02, 0.03]
    source, target = sample(20000), sample(20000) @ T[:3, :3].T + T[:3, 3]
    return source, target, T


def test_polish_lands_on_the_truth_from_a_degree_off():
    source, target, T = dense_pair()
    resolution = measure_resolution(PointIndex(source), PointIndex(target))
    assert resolution.flatness <= SMOOTH_UP_TO
    start = T.copy()
    start[:3, :3] = Rotation.from_rotvec([0.0, 0.015, 0.0]).as_matrix() @ T[:3, :3]  # 0.86° off
    start[:3, 3] += [0.004, 0.0, -0.003]
    polished = make_polish()(source, target, start, resolution)
    rot, trans = isotropic_errors(polished, T)
    before_rot, before_trans = isotropic_errors(start, T)
    assert rot < 0.1 * before_rot and trans < 0.2 * before_trans, (rot, trans)


def test_polish_declines_rough_data():
    source, target, T = dense_pair(1)
    resolution = measure_resolution(PointIndex(source), PointIndex(target))
    rough = replace(resolution, flatness=SMOOTH_UP_TO + 0.1)
    assert make_polish()(source, target, T, rough) is None


def test_polish_declines_sparse_clouds():
    """A ModelNet40-like sample (1024 points over the shape): a voxel grid of 4 spacings leaves too few points for
    covariances, so an exact result is not put at risk."""
    source, target, T = dense_pair(2)
    sparse_source, sparse_target = source[:1024], target[:1024]
    resolution = measure_resolution(PointIndex(sparse_source), PointIndex(sparse_target))
    smooth = replace(resolution, flatness=0.0)  # only the sparsity may decline it
    assert make_polish()(sparse_source, sparse_target, T, smooth) is None
