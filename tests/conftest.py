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


# --- A real HTTP service for the tests that talk to it (tests/live_server.py starts it) -------------

# Small limits keep the limit tests cheap; everything else is the service's default.
LIVE_SERVER_SETTINGS = {
    "PRANET_THREADS": "1",
    "PRANET_MAX_POINTS": "20000",
    "PRANET_MAX_BODY_BYTES": "2000000",
    "PRANET_MAX_CONCURRENCY": "2",
    "PRANET_MAX_QUEUE": "16",
    "PRANET_LOG_LEVEL": "warning",
}


@pytest.fixture(scope="session")
def live_server(tmp_path_factory: pytest.TempPathFactory):
    """``pranet-serve`` (shipped model, one worker, ``LIVE_SERVER_SETTINGS``) on a free loopback port."""
    from live_server import start_live_server

    server = start_live_server(tmp_path_factory.mktemp("live_server"), LIVE_SERVER_SETTINGS)
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture(scope="session")
def server_url(live_server) -> str:
    """Base URL of the shared live service, e.g. ``http://127.0.0.1:43121``."""
    return live_server.url
