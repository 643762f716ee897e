"""``python -m pranet.service.probe``, the containers' health check, against a real ``pranet-serve`` with an API key."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlparse

import pytest
from live_server import LiveServer, clean_env, free_port, start_live_server

API_KEY = "probe-key-0123456789"


@pytest.fixture(scope="module")
def keyed_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    server = start_live_server(tmp_path_factory.mktemp("probe"), {"PRANET_API_KEY": API_KEY, "PRANET_THREADS": "1"})
    yield server
    server.stop()


def probe(check: str, port: int, api_key: str | None) -> subprocess.CompletedProcess:
    env = clean_env({"PRANET_PORT": str(port)} | ({"PRANET_API_KEY": api_key} if api_key else {}))
    cmd = [sys.executable, "-m", "pranet.service.probe", check]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=30, env=env, cwd=Path(__file__).parent)


def port_of(server: LiveServer) -> int:
    return int(urlparse(server.url).port or 0)


def test_ready_with_the_services_key_passes(keyed_server: LiveServer) -> None:
    done = probe("ready", port_of(keyed_server), API_KEY)
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""


@pytest.mark.parametrize("api_key", [None, "wrong-key"])
def test_ready_without_the_key_fails_with_the_reason(keyed_server: LiveServer, api_key: str | None) -> None:
    done = probe("ready", port_of(keyed_server), api_key)
    assert done.returncode == 1
    assert "HTTP 401" in done.stderr


def test_health_needs_no_key(keyed_server: LiveServer) -> None:
    assert probe("health", port_of(keyed_server), None).returncode == 0


def test_no_service_fails() -> None:
    done = probe("ready", free_port(), None)
    assert done.returncode == 1
    assert "refused" in done.stderr.lower()


def test_unknown_check_is_a_usage_error() -> None:
    done = probe("alive", free_port(), None)
    assert done.returncode == 2 and "usage" in done.stderr
