"""Settings from PRANET_* environment variables, and their round trip to the workers' environment."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from pranet.service.settings import Settings


def test_defaults(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in Settings.model_fields:
        monkeypatch.delenv(f"PRANET_{name.upper()}", raising=False)
    s = Settings()
    assert (s.model_dir, s.host, s.port, s.workers, s.threads) == (None, "127.0.0.1", 8000, 1, 2)
    assert (s.max_points, s.request_timeout_s, s.max_concurrency, s.max_queue) == (1_200_000, 30.0, 2, 4)
    assert (s.max_list_points, s.max_body_bytes, s.body_timeout_s) == (200_000, None, 20.0)
    assert s.body_limit_bytes == 38_465_536  # derived: 2 clouds x 16 base64 characters x 1.2M points + 64 kB
    assert s.api_key is None and s.cors_origins == []


def test_environment_and_overrides(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PRANET_PORT", "9001")
    monkeypatch.setenv("PRANET_MODEL_DIR", "/models/v2")
    monkeypatch.setenv("PRANET_CORS_ORIGINS", "https://a.example, https://b.example")
    monkeypatch.setenv("PRANET_API_KEY", "")
    s = Settings(port=9002)  # a CLI flag wins over the environment
    assert s.port == 9002 and s.model_dir == Path("/models/v2") and s.api_key is None
    assert s.cors_origins == ["https://a.example", "https://b.example"]
    monkeypatch.setenv("PRANET_CORS_ORIGINS", '["https://c.example"]')
    assert Settings().cors_origins == ["https://c.example"]


def test_round_trip_through_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    s = Settings(model_dir="/m", api_key="k", cors_origins=["https://a.example"], max_queue=0, request_timeout_s=0.5)
    for key, value in s.to_env().items():
        if value is None:
            monkeypatch.delenv(key, raising=False)
        else:
            monkeypatch.setenv(key, value)
    assert Settings() == s


@pytest.mark.parametrize(
    "bad", [{"threads": 0}, {"port": 70000}, {"max_concurrency": 0}, {"request_timeout_s": 0}, {"log_level": "loud"}]
)
def test_invalid_values(bad: dict) -> None:
    with pytest.raises(ValidationError):
        Settings(**bad)
