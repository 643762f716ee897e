"""pranet.client.client: encoding choice, the request it sends, response parsing and error mapping."""

from __future__ import annotations

import base64
import json
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from client_helpers import canned_response, make_transform
from live_server import free_port
from numpy.testing import assert_allclose, assert_array_equal

from pranet.client import (
    PranetClient,
    PranetConnectionError,
    PranetError,
    RegistrationResult,
    encode_cloud,
    write_point_cloud,
)
from pranet.client.client import COMPACT_ENCODING, DEFAULT_COMPACT_THRESHOLD


def decode(value: Any) -> np.ndarray:
    """The service's view of an encoded cloud: ``(N, 3)``."""
    if isinstance(value, dict):
        assert value["encoding"] == COMPACT_ENCODING
        return np.frombuffer(base64.b64decode(value["data"]), dtype="<f4").reshape(-1, 3)
    return np.asarray(value, dtype=np.float64)


def test_small_clouds_are_json_lists() -> None:
    p = np.random.default_rng(0).normal(size=(DEFAULT_COMPACT_THRESHOLD, 3))
    encoded = encode_cloud(p)
    assert isinstance(encoded, list) and len(encoded) == DEFAULT_COMPACT_THRESHOLD
    assert_array_equal(decode(encoded), p)  # exact: JSON floats keep float64


def test_large_clouds_are_base64_float32_little_endian() -> None:
    p = np.random.default_rng(0).normal(size=(DEFAULT_COMPACT_THRESHOLD + 1, 3))
    encoded = encode_cloud(p)
    assert set(encoded) == {"encoding", "data"}
    raw = base64.b64decode(encoded["data"])
    assert len(raw) == p.size * 4
    assert_array_equal(decode(encoded), p.astype(np.float32))
    assert len(json.dumps(encoded)) < len(json.dumps(p.tolist())) / 2


def test_threshold_is_configurable() -> None:
    p = np.zeros((10, 3))
    assert isinstance(encode_cloud(p, compact_threshold=9), dict)
    assert isinstance(encode_cloud(p, compact_threshold=10), list)


class Recorder:
    """An ``httpx.MockTransport`` handler answering with a fixed status and body; keeps the requests."""

    def __init__(self, status: int = 200, body: Any = None, text: str | None = None) -> None:
        self.status, self.body, self.text = status, body, text
        self.requests: list[httpx.Request] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        if self.text is not None:
            return httpx.Response(self.status, text=self.text)
        return httpx.Response(self.status, json=self.body)

    def client(self, **kwargs: Any) -> PranetClient:
        return PranetClient("http://service.test", transport=httpx.MockTransport(self), **kwargs)

    @property
    def sent(self) -> dict[str, Any]:
        return json.loads(self.requests[-1].content)


T_KNOWN = make_transform(12.0, (1.0, 2.0, 3.0), (0.1, -0.2, 0.3))


def test_register_sends_contract_and_parses_result() -> None:
    rec = Recorder(body={**canned_response(T_KNOWN), "confidence": 0.75, "status": "ok"})
    rng = np.random.default_rng(1)
    source, target = rng.normal(size=(100, 3)), rng.normal(size=(6000, 3))
    with rec.client(api_key="s3cret") as client:
        result = client.register(source, target, icp=False, seed=3, steps=None, return_trajectory=True)
    request = rec.requests[-1]
    assert request.method == "POST" and request.url.path == "/register"
    assert request.headers["Authorization"] == "Bearer s3cret"
    sent = rec.sent
    assert sent["icp"] is False and sent["seed"] == 3 and sent["return_trajectory"] is True
    assert "steps" not in sent  # None means: the server's default
    assert isinstance(sent["source"], list)  # 100 points: plain JSON
    assert sent["target"]["encoding"] == COMPACT_ENCODING  # 6000 points: compact
    assert_allclose(decode(sent["target"]), target, atol=1e-6)

    assert isinstance(result, RegistrationResult)
    assert_allclose(result.transform, T_KNOWN)
    assert_allclose(result.rotation, T_KNOWN[:3, :3])
    assert_allclose(result.translation, T_KNOWN[:3, 3])
    assert [s.step for s in result.trajectory] == [1, 2, 3]
    assert_allclose(result.trajectory[-1].transform, T_KNOWN)
    assert result.icp == {"applied": True, "fitness": 0.9, "inlier_rmse": 0.001}
    assert result.timing_ms["total"] == 6.0 and result.model["name"] == "fake"
    assert result.confidence == 0.75 and result.status == "ok"
    assert result.raw["model"]["version"] == "0"


def test_register_reads_files(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    src, tgt = rng.normal(size=(50, 3)), rng.normal(size=(60, 3))
    write_point_cloud(tmp_path / "s.ply", src)
    np.save(tmp_path / "t.npy", tgt)
    rec = Recorder(body=canned_response(np.eye(4)))
    with rec.client() as client:
        result = client.register(tmp_path / "s.ply", str(tmp_path / "t.npy"))
    assert rec.sent["icp"] is True
    assert "Authorization" not in rec.requests[-1].headers
    assert_allclose(decode(rec.sent["source"]), src)
    assert_allclose(decode(rec.sent["target"]), tgt)
    assert result.confidence is None and result.status is None


def test_register_rejects_bad_arrays() -> None:
    with Recorder().client() as client, pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        client.register(np.zeros((4, 2)), np.zeros((4, 3)))


@pytest.mark.parametrize(
    ("status", "body", "text", "expected"),
    [
        (422, {"detail": [{"loc": ["body", "source"], "msg": "too few points"}]}, None, "source: too few points"),
        (401, {"detail": "missing or invalid API key"}, None, "HTTP 401 from /register: missing or invalid API key"),
        (413, {"detail": {"message": "body too large"}}, None, "body too large"),
        (503, {"error": "queue full"}, None, "queue full"),
        (500, None, "Internal Server Error", "HTTP 500 from /register: Internal Server Error"),
    ],
)
def test_http_errors_carry_the_servers_message(status: int, body: Any, text: str | None, expected: str) -> None:
    rec = Recorder(status, body, text)
    with rec.client() as client, pytest.raises(PranetError) as info:
        client.register(np.eye(3), np.eye(3))
    assert expected in str(info.value)
    assert info.value.status_code == status
    assert not isinstance(info.value, PranetConnectionError)


def test_unexpected_body_is_a_pranet_error() -> None:
    with Recorder(body={"transform": [[1, 0], [0, 1]]}).client() as client, pytest.raises(PranetError, match="4, 4"):
        client.register(np.eye(3), np.eye(3))
    with Recorder(text="<html>").client() as client, pytest.raises(PranetError, match="not JSON"):
        client.health()


def test_transport_errors_are_connection_errors() -> None:
    def refuse(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("connection refused", request=request)

    def slow(request: httpx.Request) -> httpx.Response:
        raise httpx.ReadTimeout("timed out", request=request)

    with PranetClient("http://x.test", transport=httpx.MockTransport(refuse)) as client:
        with pytest.raises(PranetConnectionError, match="cannot reach the service at http://x.test"):
            client.health()
    with PranetClient("http://x.test", transport=httpx.MockTransport(slow)) as client:
        with pytest.raises(PranetConnectionError, match="in time"):
            client.model()


def test_unreachable_real_port() -> None:
    with PranetClient(f"http://127.0.0.1:{free_port()}", timeout=5.0) as client:
        with pytest.raises(PranetConnectionError) as info:
            client.health()
    assert info.value.status_code is None


def test_status_routes_and_wait_ready() -> None:
    calls = {"n": 0}

    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/ready":
            calls["n"] += 1
            if calls["n"] < 3:
                return httpx.Response(503, json={"detail": "model loading"})
            return httpx.Response(200, json={"status": "ready"})
        return httpx.Response(200, json={"path": request.url.path})

    with PranetClient("http://x.test/", transport=httpx.MockTransport(handler)) as client:
        assert client.health() == {"path": "/health"}
        assert client.model() == {"path": "/model"}
        with pytest.raises(PranetError, match="model loading") as info:
            client.ready()
        assert info.value.status_code == 503
        assert client.wait_ready(timeout=5.0, interval=0.01) == {"status": "ready"}


def test_the_client_result_has_every_field_of_the_response_schema() -> None:
    """Contract: a field the service adds to ``RegisterResponse`` must reach ``RegistrationResult`` (and back)."""
    import dataclasses

    pytest.importorskip("fastapi")
    from pranet.client.client import RegistrationResult
    from pranet.service.schemas import RegisterResponse

    client_fields = {f.name for f in dataclasses.fields(RegistrationResult)} - {"raw"}
    assert client_fields == set(RegisterResponse.model_fields)
    body = {
        "transform": np.eye(4).tolist(),
        "rotation": np.eye(3).tolist(),
        "translation": [0.0, 0.0, 0.0],
        "trajectory": [],
        "icp": {"applied": True, "fitness": 1.0, "inlier_rmse": 0.0},
        "timing_ms": {"total": 1.0},
        "model": {"name": "m", "version": "1", "sha256": "0" * 64},
        "n_source": 10,
        "n_target": 12,
        "confidence": 0.9,
        "status": "converged",
        "matches": 40,
        "initial_transform": np.eye(4).tolist(),
        "exit_checks": [{"step": 20, "confidence": 0.9}],
        "rescued": "restarts",
        "candidate": "restarts",
        "candidates": {"agent": 0.2, "global_match": 0.3, "restarts": 0.9},
        "spacing": 0.0005,
        "network_calls": 7,
    }
    RegisterResponse.model_validate(body)  # a valid response...
    result = RegistrationResult.from_json(body)  # ...read field by field
    for name in client_fields:
        value = getattr(result, name)
        expected = body[name]
        if isinstance(value, np.ndarray):
            np.testing.assert_allclose(value, expected)
        else:
            assert value == expected, name
