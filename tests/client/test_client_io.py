"""pranet.client.io: round trips of every format, and one clear error per kind of bad file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from pranet.client.io import PointCloudIOError, read_point_cloud, write_point_cloud


@pytest.fixture
def points() -> np.ndarray:
    return np.random.default_rng(0).normal(scale=0.3, size=(257, 3))  # (N, 3)


@pytest.mark.parametrize(
    ("suffix", "ascii", "atol"),
    [
        (".ply", False, 0.0),  # Open3D writes doubles
        (".ply", True, 1e-5),  # text with ~6 significant digits
        (".pcd", False, 1e-6),  # float32
        (".pcd", True, 1e-6),
        (".xyz", False, 1e-9),
        (".npy", False, 0.0),
    ],
)
def test_round_trip(tmp_path: Path, points: np.ndarray, suffix: str, ascii: bool, atol: float) -> None:
    path = write_point_cloud(tmp_path / f"cloud{suffix}", points, ascii=ascii)
    back = read_point_cloud(path)
    assert back.shape == points.shape and back.dtype == np.float64
    assert_allclose(back, points, rtol=0, atol=atol)


def test_reads_upper_case_suffix_and_str_path(tmp_path: Path, points: np.ndarray) -> None:
    path = write_point_cloud(tmp_path / "CLOUD.PLY", points)
    assert_allclose(read_point_cloud(str(path)), points)


def test_reads_real_scan_with_extra_elements(scans_dir: Path) -> None:
    cloud = read_point_cloud(scans_dir / "bun000.ply")  # ASCII PLY with a range_grid element
    assert cloud.shape == (40256, 3)
    assert np.isfinite(cloud).all()


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("garbage.ply", b"not a ply file\n", "not a valid PLY file"),
        ("truncated.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n1\n", "PLY"),
        ("garbage.pcd", b"hello\n", "no points could be read"),
        ("garbage.xyz", b"a b c\n", "no points could be read"),
        ("empty.ply", b"", "empty file"),
        ("garbage.npy", b"\x00\x01 nothing", "not a valid .npy file"),
        ("cloud.txt", b"1 2 3\n", "unsupported file type"),
    ],
)
def test_bad_files_raise_one_clear_error(
    tmp_path: Path, capfd: pytest.CaptureFixture[str], name: str, content: bytes, message: str
) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(PointCloudIOError, match=message) as info:
        read_point_cloud(path)
    assert str(path) in str(info.value)
    assert "\n" not in str(info.value)
    captured = capfd.readouterr()
    assert captured.out == "" and captured.err == ""  # Open3D/RPly console output is swallowed


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(PointCloudIOError, match="no such file"):
        read_point_cloud(tmp_path / "absent.ply")


def test_directory_is_not_a_cloud(tmp_path: Path) -> None:
    with pytest.raises(PointCloudIOError, match="not a regular file"):
        read_point_cloud(tmp_path)


@pytest.mark.parametrize(
    ("array", "message"),
    [
        (np.zeros((5, 2)), r"shape \(N, 3\)"),
        (np.zeros((0, 3)), "no points"),
        (np.array([[0.0, np.nan, 1.0]]), "NaN"),
    ],
)
def test_bad_npy_contents(tmp_path: Path, array: np.ndarray, message: str) -> None:
    path = tmp_path / "cloud.npy"
    np.save(path, array)
    with pytest.raises(PointCloudIOError, match=message):
        read_point_cloud(path)


def test_write_rejects_bad_input(tmp_path: Path, points: np.ndarray) -> None:
    with pytest.raises(PointCloudIOError, match="does not exist"):
        write_point_cloud(tmp_path / "missing" / "cloud.ply", points)
    with pytest.raises(PointCloudIOError, match="unsupported file type"):
        write_point_cloud(tmp_path / "cloud.obj", points)
    with pytest.raises(PointCloudIOError, match="no points"):
        write_point_cloud(tmp_path / "cloud.ply", np.zeros((0, 3)))
