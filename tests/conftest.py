"""Shared fixtures. Data comes from one configurable root: ``$PRANET_DATA_DIR``, default ``../shared/data``
relative to the repository root; tests that need it skip with the reason when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA_ROOT = REPO_ROOT.parent / "shared" / "data"


def _data_root() -> Path:
    return Path(os.environ.get("PRANET_DATA_DIR") or DEFAULT_DATA_ROOT)


@pytest.fixture(scope="session")
def data_root() -> Path:
    root = _data_root()
    if not (root / "modelnet40" / "test.h5").exists() and not list(root.glob("modelnet40_ply_hdf5_2048/*.h5")):
        pytest.skip(f"ModelNet40 not found under {root} (set PRANET_DATA_DIR)")
    return root


@pytest.fixture(scope="session")
def scans_dir() -> Path:
    d = _data_root() / "scans"
    if not (d / "bun000.ply").exists():
        pytest.skip(f"scans not found under {d} (set PRANET_DATA_DIR)")
    return d
