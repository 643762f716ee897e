"""Operations over real HTTP: API key, time limit (504), capacity (503), SIGTERM, refusing bad models."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest
from live_server import LiveServer, clean_env, console_script, free_port, start_live_server
from service_helpers import b64, synthetic_pair

from pranet.engine.runtime import default_model_dir

API_KEY = "test-key-0123456789"
AUTH = {"Authorization": f"Bearer {API_KEY}"}
SLOW_STEPS = [100, 100]  # seconds of agent work on this machine: long enough to be caught in flight


def _slow_body() -> dict:
    source, target, _ = synthetic_pair(n=1000)
    return {"source": b64(source), "target": b64(target), "steps": SLOW_STEPS, "icp": False, "walk": False}


def _tiny_body() -> dict:
    source, target, _ = synthetic_pair(n=20)
    return {"source": b64(source), "target": b64(target), "steps": [0, 0], "icp": False}


def _wait_in_flight(client: httpx.Client, n: int, timeout: float = 30.0, headers: dict | None = None) -> None:
    deadline = time.monotonic() + timeout
    while client.get("/ready", headers=headers).json()["in_flight"] < n:
        assert time.monotonic() < deadline, f"no {n} registration(s) in flight after {timeout} s"
        time.sleep(0.02)


# --- API key and time limit: one server with both ------------------------------------------------------


@pytest.fixture(scope="module")
def guarded_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    settings = {"PRANET_API_KEY": API_KEY, "PRANET_REQUEST_TIMEOUT_S": "0.05", "PRANET_THREADS": "1"}
    server = start_live_server(tmp_path_factory.mktemp("guarded"), settings)
    yield server
    server.stop()


def test_health_needs_no_api_key(guarded_server: LiveServer) -> None:
    assert httpx.get(f"{guarded_server.url}/health").status_code == 200


@pytest.mark.parametrize(
    ("method", "path"), [("GET", "/ready"), ("GET", "/model"), ("GET", "/openapi.json"), ("POST", "/register")]
)
def test_api_key_required(guarded_server: LiveServer, method: str, path: str) -> None:
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": API_KEY}):
        body = _tiny_body() if method == "POST" else None
        r = httpx.request(method, f"{guarded_server.url}{path}", headers=headers, json=body)
        assert r.status_code == 401, (headers, r.text)
        assert r.headers["www-authenticate"] == "Bearer"
        assert "Authorization: Bearer" in r.json()["detail"]


def test_api_key_accepted(guarded_server: LiveServer) -> None:
    assert httpx.get(f"{guarded_server.url}/ready", headers=AUTH).status_code == 200
    assert httpx.get(f"{guarded_server.url}/model", headers=AUTH).json()["name"]
    schema = httpx.get(f"{guarded_server.url}/openapi.json", headers=AUTH).json()
    assert schema["components"]["securitySchemes"]["BearerAuth"] == {"type": "http", "scheme": "bearer"}
    assert schema["paths"]["/register"]["post"]["security"] == [{"BearerAuth": []}]
    assert "security" not in schema["paths"]["/health"]["get"]


def test_time_limit_gives_504(guarded_server: LiveServer) -> None:
    r = httpx.post(
        f"{guarded_server.url}/register",
        # 200 steps from 120 global starts, scored in one batch per step: about 30 s of agent work here, far past
        # 0.05 s on any machine (the model's own 60 steps from one start made 31 network calls in 53 ms here, and
        # finished inside the limit on CI)
        json={**_slow_body(), "exit_checks": [], "init": "global", "starts": 120},
        headers=AUTH,
        timeout=60,
    )
    assert r.status_code == 504
    assert "time limit" in r.json()["detail"]
    assert httpx.get(f"{guarded_server.url}/ready", headers=AUTH).json()["in_flight"] == 0


# --- Capacity and graceful shutdown: one registration at a time, no queue ---------------------------------

ONE_AT_A_TIME = {"PRANET_MAX_CONCURRENCY": "1", "PRANET_MAX_QUEUE": "0", "PRANET_THREADS": "1"}


def test_over_capacity_gives_503_at_once(tmp_path: Path) -> None:
    server = start_live_server(tmp_path, ONE_AT_A_TIME)
    try:
        with httpx.Client(base_url=server.url, timeout=120) as client, ThreadPoolExecutor(4) as pool:
            slow = pool.submit(client.post, "/register", json=_slow_body())
            _wait_in_flight(client, 1)
            started = time.monotonic()
            burst = [pool.submit(client.post, "/register", json=_tiny_body()) for _ in range(3)]
            refused = [f.result() for f in burst]
            assert time.monotonic() - started < 5.0  # refused at once, not queued behind the slow one
            for r in refused:
                assert r.status_code == 503
                assert "capacity" in r.json()["detail"]
                assert r.headers["retry-after"] == "1"
            assert slow.result().status_code == 200
            assert client.post("/register", json=_tiny_body()).status_code == 200  # capacity is back
    finally:
        server.stop()


def test_sigterm_lets_the_in_flight_request_finish(tmp_path: Path) -> None:
    server = start_live_server(tmp_path, ONE_AT_A_TIME)
    try:
        with httpx.Client(base_url=server.url, timeout=120) as client:
            result: dict[str, httpx.Response] = {}
            worker = threading.Thread(target=lambda: result.update(r=client.post("/register", json=_slow_body())))
            worker.start()
            _wait_in_flight(client, 1)
            server.terminate()
            worker.join(timeout=120)
            assert result["r"].status_code == 200, result["r"].text
            assert len(result["r"].json()["trajectory"]) == sum(SLOW_STEPS)
        code = server.process.wait(timeout=30)
        assert code in (0, -signal.SIGTERM)  # uvicorn re-raises the signal once it has shut down cleanly
        assert "Finished server process" in server.output()
        with pytest.raises(httpx.TransportError):
            httpx.get(f"{server.url}/health", timeout=2)
    finally:
        server.stop()


# --- pranet-serve refuses to start on a bad model -----------------------------------------------------------


def _serve(*args: str, **settings: str) -> subprocess.CompletedProcess:
    cmd = [console_script("pranet-serve"), "--host", "127.0.0.1", "--port", str(free_port()), *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=clean_env(settings))


def _copy_model(tmp_path: Path) -> Path:
    model = tmp_path / "model"
    shutil.copytree(default_model_dir(), model)
    return model


def _flip_bytes(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2 : len(data) // 2 + 64] = bytes(64)
    path.write_bytes(bytes(data))


def _edit_card(model: Path, edit) -> None:
    card = json.loads((model / "card.json").read_text())
    edit(card)
    (model / "card.json").write_text(json.dumps(card))


def _sha256(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


def _corrupt_graph_keep_card_consistent(model: Path) -> None:
    (model / "score.onnx").write_bytes(b"this is not an onnx graph")
    _edit_card(model, lambda c: c["files"].update({"score.onnx": _sha256(model / "score.onnx")}))


CORRUPTIONS = {
    "missing directory": (lambda m: shutil.rmtree(m), "no model card at"),
    "missing graph": (lambda m: (m / "embed.onnx").unlink(), "missing model graph"),
    "corrupt graph (sha256)": (lambda m: _flip_bytes(m / "embed.onnx"), "sha256 does not match the model card"),
    "corrupt graph (onnx)": (_corrupt_graph_keep_card_consistent, "onnxruntime cannot load"),
    "unreadable card": (lambda m: (m / "card.json").write_text("{not json"), "unreadable model card"),
    "card without actions": (lambda m: _edit_card(m, lambda c: c.pop("actions")), "invalid model card"),
    "action table mismatch": (
        lambda m: _edit_card(m, lambda c: c["actions"].update(fingerprint="0" * 64)),
        "action table mismatch",
    ),
}


@pytest.mark.parametrize("case", list(CORRUPTIONS))
def test_serve_refuses_a_bad_model(tmp_path: Path, case: str) -> None:
    corrupt, message = CORRUPTIONS[case]
    model = _copy_model(tmp_path)
    corrupt(model)
    done = _serve("--model", str(model))
    assert done.returncode == 1, done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("pranet-serve: error: ") and message in lines[0]
    assert "Traceback" not in done.stdout + done.stderr


def test_serve_refuses_a_bad_model_from_the_environment(tmp_path: Path) -> None:
    done = _serve(PRANET_MODEL_DIR=str(tmp_path / "nowhere"))
    assert done.returncode == 1
    assert "no model card at" in done.stderr and "Traceback" not in done.stderr


@pytest.mark.parametrize(
    ("args", "settings", "message"),
    [(("--threads", "0"), {}, "threads"), ((), {"PRANET_MAX_POINTS": "lots"}, "max_points")],
)
def test_serve_refuses_invalid_settings(args: tuple, settings: dict, message: str) -> None:
    done = _serve(*args, **settings)
    assert done.returncode == 1
    assert done.stderr.startswith("pranet-serve: error: invalid settings") and message in done.stderr
    assert "Traceback" not in done.stderr
