"""Read and write point clouds: PLY, PCD and XYZ through Open3D, NPY through NumPy.

Every reader returns ``points: (N, 3) float64`` or raises ``PointCloudIOError`` (a ``ValueError``)
with a message that names the file and says what is wrong: missing, unreadable, empty, wrong shape
or non-finite values. Open3D's own console warnings are silenced while reading, so that a CLI can
print exactly one line per error.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

OPEN3D_SUFFIXES = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")
NUMPY_SUFFIXES = (".npy",)
SUPPORTED_SUFFIXES = OPEN3D_SUFFIXES + NUMPY_SUFFIXES


class PointCloudIOError(ValueError):
    """A point cloud file is missing, unreadable, empty or malformed."""


def _suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise PointCloudIOError(
            f"{path}: unsupported file type {suffix or '(no suffix)'!r}; use one of {', '.join(SUPPORTED_SUFFIXES)}"
        )
    return suffix


def _check_points(points: npt.ArrayLike, path: Path) -> Array:
    """``points`` as ``(N, 3)`` float64, non-empty and finite, or raise naming ``path``."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise PointCloudIOError(f"{path}: expected an array of shape (N, 3), got {p.shape}")
    if len(p) == 0:
        raise PointCloudIOError(f"{path}: no points")
    if not np.isfinite(p).all():
        raise PointCloudIOError(f"{path}: contains NaN or infinite coordinates")
    return p


@contextlib.contextmanager
def _captured_native_stderr(messages: list[str]) -> Iterator[None]:
    """Collect what native code (Open3D's PLY reader, RPly) writes to file descriptor 2 into ``messages``.

    RPly prints its errors straight to the C ``stderr``; capturing them keeps a CLI's error to one line
    and lets the reader turn them into an exception. Not thread-safe with other writers to fd 2.
    """
    fd = 2  # the C library's stderr, whatever Python's sys.stderr was replaced with
    for stream in (sys.stderr, sys.__stderr__):
        if stream is not None:
            stream.flush()
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        saved = os.dup(fd)
        try:
            os.dup2(tmp.fileno(), fd)
            yield
        finally:
            os.dup2(saved, fd)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode("utf-8", errors="replace")
            messages.extend(line.strip() for line in text.splitlines() if line.strip())


def read_point_cloud(path: str | os.PathLike[str]) -> Array:
    """Read ``path`` (.ply, .pcd, .xyz, .xyzn, .xyzrgb, .pts or .npy) -> ``(N, 3)`` float64 points.

    Only the coordinates are kept (colours and normals are dropped). Raises ``PointCloudIOError``.
    """
    path = Path(path)
    if not path.exists():
        raise PointCloudIOError(f"{path}: no such file")
    if not path.is_file():
        raise PointCloudIOError(f"{path}: not a regular file")
    suffix = _suffix(path)
    if path.stat().st_size == 0:
        raise PointCloudIOError(f"{path}: empty file")
    if suffix in NUMPY_SUFFIXES:
        try:
            arr = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as e:
            raise PointCloudIOError(f"{path}: not a valid .npy file") from e
        return _check_points(arr, path)

    import open3d as o3d

    # Open3D reports unreadable files as console warnings and an empty cloud, and its PLY reader prints
    # parse errors (truncated files) to the C stderr: silence both, and treat a parse error as fatal.
    native: list[str] = []
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error), _captured_native_stderr(native):
        try:
            cloud = o3d.io.read_point_cloud(str(path), format="auto", remove_nan_points=False)
        except (RuntimeError, ValueError) as e:
            raise PointCloudIOError(f"{path}: Open3D cannot read it ({e})") from e
    if native:
        raise PointCloudIOError(f"{path}: not a valid {suffix[1:].upper()} file ({native[0]})")
    points = np.asarray(cloud.points)
    if len(points) == 0:
        raise PointCloudIOError(f"{path}: no points could be read (empty or not a valid {suffix[1:].upper()} file)")
    return _check_points(points, path)


def write_point_cloud(path: str | os.PathLike[str], points: npt.ArrayLike, ascii: bool = False) -> Path:
    """Write ``points: (N, 3)`` to ``path``; the format follows the suffix. Returns ``path``.

    ``ascii`` applies to PLY and PCD (XYZ is always text, NPY always binary). Parent folders must exist.
    """
    path = Path(path)
    suffix = _suffix(path)
    p = _check_points(points, path)
    if not path.parent.is_dir():
        raise PointCloudIOError(f"{path}: folder {path.parent} does not exist")
    if suffix in NUMPY_SUFFIXES:
        try:
            np.save(path, p)
        except OSError as e:
            raise PointCloudIOError(f"{path}: cannot write ({e})") from e
        return path

    import open3d as o3d

    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.ascontiguousarray(p))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        ok = o3d.io.write_point_cloud(str(path), cloud, write_ascii=ascii)
    if not ok:
        raise PointCloudIOError(f"{path}: Open3D could not write the file (permissions or disk space?)")
    return path
