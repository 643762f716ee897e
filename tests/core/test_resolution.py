"""core.resolution: the data's spacing and flatness, against oracles with a known sampling."""

import numpy as np
import pytest

from pranet.core.resolution import Resolution, flatness, measure_resolution, median_spacing, smallest_eigenvalues


def grid(step: float, n: int = 60) -> np.ndarray:
    """A flat square lattice of ``n x n`` points ``step`` apart (z = 0)."""
    u = np.arange(n) * step
    x, y = np.meshgrid(u, u)
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)


def test_the_spacing_of_a_lattice_is_its_step_in_any_units():
    assert median_spacing(grid(0.002)) == pytest.approx(0.002)
    assert median_spacing(grid(2.0)) == pytest.approx(2.0)


def test_duplicated_points_do_not_hide_the_spacing():
    g = grid(0.01)
    assert median_spacing(np.concatenate([g, g])) == pytest.approx(0.01)


def test_a_partly_duplicated_cloud_keeps_its_spacing_where_some_points_repeat_more_than_once():
    g = grid(0.01)
    assert median_spacing(np.concatenate([g, g[:100], g[:100], g[:100]])) == pytest.approx(0.01)


def test_the_smallest_eigenvalues_are_lapacks():
    """Against ``numpy.linalg.eigvalsh`` on covariances of every rank (3, 2, 1, 0) and a repeated eigenvalue."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(400, 3, 3))
    c = a @ a.transpose(0, 2, 1)
    c[1::4] = a[1::4, :, :2] @ a[1::4, :, :2].transpose(0, 2, 1)  # rank 2: smallest 0
    c[2::4] = a[2::4, :, :1] @ a[2::4, :, :1].transpose(0, 2, 1)  # rank 1
    c[3::8] = 0.0
    c[7::8] = np.eye(3) * 2.0
    expected = np.maximum(np.linalg.eigvalsh(c)[:, 0], 0.0)
    np.testing.assert_allclose(smallest_eigenvalues(c), expected, atol=1e-9 * np.abs(c).max())


def test_the_pair_takes_the_coarser_spacing_and_scales_with_the_units():
    r = measure_resolution(grid(0.5), grid(1.0))
    assert r.spacing == pytest.approx(1.0)
    assert r.voxel == pytest.approx(4.0) and r.feature_radius == pytest.approx(20.0)
    assert r.scaled(1e-3).spacing == pytest.approx(1e-3) and r.scaled(1e-3).flatness == r.flatness


def test_flatness_is_zero_on_a_plane_and_grows_with_noise_against_the_spacing():
    rng = np.random.default_rng(0)
    plane = grid(0.01)
    assert flatness(plane, 0.01) == pytest.approx(0.0, abs=1e-9)
    noisy = plane + np.array([0.0, 0.0, 1.0]) * rng.normal(0.0, 0.005, (len(plane), 1))  # half a spacing
    assert 0.25 < flatness(noisy, 0.01) < 0.6
    assert flatness(noisy, 0.01) == pytest.approx(flatness(1000 * noisy, 10.0))  # unit-free


def test_a_default_resolution_counts_as_flat():
    assert Resolution(0.1).flatness == 0.0
