"""core.resolution: the data's spacing, flatness and planarity, against oracles with a known sampling."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pranet.core.resolution import (
    Resolution,
    flatness,
    measure_resolution,
    median_spacing,
    planarity,
    smallest_eigenvalues,
)


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
    assert r.scaled(1e-3).planarity == r.planarity


def test_flatness_is_zero_on_a_plane_and_grows_with_noise_against_the_spacing():
    rng = np.random.default_rng(0)
    plane = grid(0.01)
    assert flatness(plane, 0.01) == pytest.approx(0.0, abs=1e-9)
    noisy = plane + np.array([0.0, 0.0, 1.0]) * rng.normal(0.0, 0.005, (len(plane), 1))  # half a spacing
    assert 0.25 < flatness(noisy, 0.01) < 0.6
    assert flatness(noisy, 0.01) == pytest.approx(flatness(1000 * noisy, 10.0))  # unit-free


def test_a_default_resolution_counts_as_flat():
    assert Resolution(0.1).flatness == 0.0


def tilted(points: np.ndarray) -> np.ndarray:
    return points @ Rotation.from_rotvec([0.7, -0.4, 0.3]).as_matrix().T + [0.3, -0.2, 0.5]


def test_planarity_is_the_rms_distance_to_the_best_plane_in_spacings():
    """0 on a tilted lattice; a lattice whose points alternate +-h off its plane is h away (RMS, to 0.1 %: the best
    plane tilts a little towards the columns)."""
    plane = grid(0.01)
    assert planarity(tilted(plane), 0.01) == pytest.approx(0.0, abs=1e-9)
    bent = plane + np.array([0.0, 0.0, 1.0]) * np.where(np.arange(len(plane)) % 2, 0.003, -0.003)[:, None]
    assert planarity(tilted(bent), 0.01, probes=len(plane)) == pytest.approx(0.3, rel=1e-3)
    assert planarity(1000 * tilted(bent), 10.0, probes=len(plane)) == pytest.approx(0.3, rel=1e-3)  # unit-free
    assert planarity(plane, 0.0) == float("inf")


def test_a_plane_clean_or_under_noise_is_planar_and_not_smooth_and_a_sphere_is_neither_planar_nor_flat():
    rng = np.random.default_rng(0)
    plane = tilted(grid(0.01))
    clean = measure_resolution(plane, plane)
    assert clean.planar and not clean.smooth  # normals all one: ICP must not finish point-to-plane
    noisy_plane = plane + rng.normal(0.0, 0.005, plane.shape)  # half a spacing of noise in every direction
    noisy = measure_resolution(noisy_plane, noisy_plane)
    assert noisy.planarity > 0.25 and noisy.planar
    u = rng.standard_normal((4000, 3))
    sphere = u / np.linalg.norm(u, axis=1, keepdims=True)
    round_ = measure_resolution(sphere, sphere)
    assert not round_.planar and round_.planarity > 10
    noisy_sphere = sphere + rng.normal(0.0, 0.5 * round_.spacing, sphere.shape)  # as rough as the noisy plane
    assert not measure_resolution(noisy_sphere, noisy_sphere).planar


def test_an_unmeasured_planarity_is_not_planar():
    assert not Resolution(0.1).planar and Resolution(0.1).smooth
    assert not Resolution(0.1, flatness=float("inf")).planar
