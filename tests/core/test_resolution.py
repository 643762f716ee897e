"""core.resolution: the data's spacing and flatness, against oracles with a known sampling."""

import numpy as np
import pytest

from pranet.core.resolution import Resolution, flatness, measure_resolution, median_spacing


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
