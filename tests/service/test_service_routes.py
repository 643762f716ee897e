"""Every route of the service over real HTTP (a live ``pranet-serve``), and registration against ground truth."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import httpx
import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation
from service_helpers import FEW_STEPS, b64, rotation_error_deg, synthetic_pair

from pranet.core.registration_config import PAPER_AGENT_POINTS


def test_health_is_open_and_minimal(http: httpx.Client) -> None:
    r = http.get("/health")
    assert r.status_code == 200
    assert r.json() == {"status": "ok"}


def test_ready_reports_the_model_and_capacity(http: httpx.Client) -> None:
    r = http.get("/ready")
    assert r.status_code == 200
    body = r.json()
    assert body["status"] == "ready"
    assert set(body["model"]) == {"name", "version", "sha256"}
    assert len(body["model"]["sha256"]) == 64
    assert body["max_concurrency"] == 2 and body["max_queue"] == 16


def test_model_card(http: httpx.Client) -> None:
    card = http.get("/model").json()
    assert card["sha256"] == http.get("/ready").json()["model"]["sha256"]
    for key in ("name", "version", "actions", "schedule", "n_points"):
        assert key in card
    assert len(card["actions"]["names"]) == 12 * len(card["actions"]["scales"])


def test_openapi_documents_both_cloud_encodings(http: httpx.Client) -> None:
    schema = http.get("/openapi.json").json()
    assert {"/health", "/ready", "/model", "/register"} <= set(schema["paths"])
    body = schema["paths"]["/register"]["post"]["requestBody"]["content"]["application/json"]["schema"]
    assert body == {"$ref": "#/components/schemas/RegisterRequest"}
    request = schema["components"]["schemas"]["RegisterRequest"]
    assert request["additionalProperties"] is False
    variants = request["properties"]["source"]["oneOf"]
    assert {"$ref": "#/components/schemas/EncodedCloud"} in variants
    assert any(v.get("type") == "array" for v in variants)
    encoded = schema["components"]["schemas"]["EncodedCloud"]
    assert encoded["properties"]["encoding"]["const"] == "base64-float32-le"
    for status in ("413", "415", "422", "503", "504"):
        assert status in schema["paths"]["/register"]["post"]["responses"]


def test_docs_page(http: httpx.Client) -> None:
    r = http.get("/docs")
    assert r.status_code == 200
    assert "swagger" in r.text.lower()


def test_unknown_route_is_a_json_404(http: httpx.Client) -> None:
    r = http.get("/nope")
    assert r.status_code == 404
    assert r.json() == {"detail": "Not Found"}


def test_register_recovers_a_known_transform(http: httpx.Client) -> None:
    source, target, T_gt = synthetic_pair()
    r = http.post("/register", json={"source": source.tolist(), "target": target.tolist(), "steps": FEW_STEPS})
    assert r.status_code == 200, r.text
    body = r.json()
    assert set(body) >= {
        "transform",
        "rotation",
        "translation",
        "trajectory",
        "icp",
        "timing_ms",
        "model",
        "n_source",
        "n_target",
    }
    T = np.array(body["transform"])
    assert T.shape == (4, 4)
    assert_allclose(T[3], [0, 0, 0, 1])
    assert_allclose(np.array(body["rotation"]), T[:3, :3])
    assert_allclose(body["translation"], T[:3, 3])
    assert rotation_error_deg(T[:3, :3], T_gt[:3, :3]) < 0.05
    assert_allclose(T[:3, 3], T_gt[:3, 3], atol=1e-4)
    assert_allclose(source @ T[:3, :3].T + T[:3, 3], target, atol=1e-3)  # target ≈ R @ source + t
    assert body["icp"]["applied"] is True
    assert body["icp"]["fitness"] > 0.99
    assert body["icp"]["inlier_rmse"] < 1e-3
    assert body["n_source"] == body["n_target"] == len(source)
    assert [s["step"] for s in body["trajectory"]] == list(range(sum(FEW_STEPS)))
    assert all(np.array(s["transform"]).shape == (4, 4) and s["action"] for s in body["trajectory"])
    assert {"queue", "decode", "preprocess", "agent_steps", "icp", "total"} <= set(body["timing_ms"])
    assert body["model"] == http.get("/ready").json()["model"]


def test_register_default_schedule_without_icp(http: httpx.Client) -> None:
    source, target, _ = synthetic_pair(n=300)
    body = {"source": source.tolist(), "target": target.tolist(), "icp": False, "walk": False}  # the paper's steps
    r = http.post("/register", json=body)
    assert r.status_code == 200, r.text
    body = r.json()
    schedule = http.get("/model").json()["schedule"]
    assert len(body["trajectory"]) == sum(schedule)
    assert body["icp"] == {"applied": False, "fitness": None, "inlier_rmse": None}
    assert_allclose(np.array(body["trajectory"][-1]["transform"]), np.array(body["transform"]))
    R = np.array(body["rotation"])
    assert_allclose(R @ R.T, np.eye(3), atol=1e-9)


def test_list_and_base64_encodings_agree(http: httpx.Client) -> None:
    source, target, _ = synthetic_pair(n=400, seed=1)
    common = {"steps": FEW_STEPS, "seed": 7, "policy": "stoch1"}
    as_list = http.post("/register", json={"source": source.tolist(), "target": target.tolist(), **common})
    as_b64 = http.post("/register", json={"source": b64(source), "target": b64(target), **common})
    mixed = http.post("/register", json={"source": b64(source), "target": target.tolist(), **common})
    assert as_list.status_code == as_b64.status_code == mixed.status_code == 200
    for other in (as_b64.json(), mixed.json()):
        assert_allclose(np.array(other["transform"]), np.array(as_list.json()["transform"]), atol=1e-9)
        assert [s["action"] for s in other["trajectory"]] == [s["action"] for s in as_list.json()["trajectory"]]


def test_world_units_are_kept(http: httpx.Client) -> None:
    """Clouds in mm (x1000) give the same rotation and the translation in mm."""
    source, target, T_gt = synthetic_pair(n=400, seed=2)
    results = []
    for scale in (1.0, 1000.0):
        r = http.post(
            "/register",
            json={"source": b64(source * scale), "target": b64(target * scale), "steps": FEW_STEPS},
        )
        assert r.status_code == 200, r.text
        results.append(r.json())
    metres, millimetres = results
    assert_allclose(millimetres["rotation"], metres["rotation"], atol=1e-5)
    assert_allclose(millimetres["translation"], np.array(metres["translation"]) * 1000.0, rtol=1e-4, atol=1e-2)
    assert_allclose(millimetres["translation"], T_gt[:3, 3] * 1000.0, atol=0.1)
    assert millimetres["icp"]["inlier_rmse"] == pytest.approx(metres["icp"]["inlier_rmse"] * 1000.0, abs=1e-2)


def test_trajectory_can_be_left_out(http: httpx.Client) -> None:
    source, target, _ = synthetic_pair(n=200)
    r = http.post(
        "/register",
        json={"source": b64(source), "target": b64(target), "steps": [1, 1], "return_trajectory": False},
    )
    assert r.status_code == 200
    assert r.json()["trajectory"] == []


@pytest.mark.parametrize("policy", ["deterministic", "stoch1", "stoch2"])
def test_policies_and_early_stop(http: httpx.Client, policy: str) -> None:
    source, target, _ = synthetic_pair(n=200)
    r = http.post(
        "/register",
        json={"source": b64(source), "target": b64(target), "steps": [2, 2], "policy": policy, "early_stop": True},
    )
    assert r.status_code == 200, r.text
    assert len(r.json()["trajectory"]) <= 4


def test_steps_must_match_the_model_scales(http: httpx.Client) -> None:
    source, target, _ = synthetic_pair(n=100)
    r = http.post("/register", json={"source": b64(source), "target": b64(target), "steps": [1, 1, 1]})
    assert r.status_code == 422
    assert "step-size scales" in r.json()["detail"]


def test_service_never_imports_torch() -> None:
    code = textwrap.dedent(
        """
        import sys
        from fastapi.testclient import TestClient
        from pranet.service.app import create_app
        from pranet.service.settings import Settings
        app = create_app(Settings())
        with TestClient(app) as client:
            assert client.get("/ready").status_code == 200
        assert "torch" not in sys.modules, "the service imported torch"
        """
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr


def test_ready_is_503_when_the_model_cannot_load(tmp_path) -> None:
    """Served without pranet-serve's check (e.g. plain uvicorn): the app stays up, /ready says why."""
    from fastapi.testclient import TestClient

    from pranet.service.app import create_app
    from pranet.service.settings import Settings

    app = create_app(Settings(model_dir=tmp_path / "missing"))
    with TestClient(app) as client:
        assert client.get("/health").status_code == 200
        r = client.get("/ready")
        assert r.status_code == 503
        assert "no model card" in r.json()["detail"]
        assert client.get("/model").status_code == 503
        source, target, _ = synthetic_pair(n=50)
        r = client.post("/register", json={"source": b64(source), "target": b64(target)})
        assert r.status_code == 503


def test_cors_when_origins_are_configured() -> None:
    from fastapi.testclient import TestClient

    from pranet.service.app import create_app
    from pranet.service.settings import Settings

    app = create_app(Settings(cors_origins=["https://viewer.example"], api_key="k"))
    with TestClient(app) as client:
        preflight = client.options(
            "/register",
            headers={"Origin": "https://viewer.example", "Access-Control-Request-Method": "POST"},
        )
        assert preflight.status_code == 200
        assert preflight.headers["access-control-allow-origin"] == "https://viewer.example"
        r = client.get("/health", headers={"Origin": "https://other.example"})
        assert "access-control-allow-origin" not in r.headers


def test_unexpected_errors_are_a_generic_500_without_traceback() -> None:
    from fastapi.testclient import TestClient

    from pranet.service.app import create_app
    from pranet.service.settings import Settings

    app = create_app(Settings())

    @app.get("/boom")
    def boom() -> None:
        raise RuntimeError("secret internal detail")

    with TestClient(app, raise_server_exceptions=False) as client:
        r = client.get("/boom")
    assert r.status_code == 500
    assert r.json() == {"detail": "internal server error"}


def test_exit_checks_stop_the_agent_once_icp_converges(http: httpx.Client) -> None:
    """Default request: ICP + confidence after 20 and 40 scheduled steps; a 5° pair converges at the first check
    (the walk may end the coarse phase sooner: a 10° step overshoots 5°). The paper's PRANet-v2 takes all 60."""
    source, target, T_gt = synthetic_pair(n=400)
    fast = http.post("/register", json={"source": b64(source), "target": b64(target)}).json()
    assert len(fast["exit_checks"]) == 1 and fast["exit_checks"][0]["confidence"] >= 0.55
    assert len(fast["trajectory"]) == fast["exit_checks"][0]["step"] <= 20
    assert fast["status"] == "converged" and fast["rescued"] is None
    assert rotation_error_deg(np.array(fast["rotation"]), T_gt[:3, :3]) < 0.05
    paper = {"source": b64(source), "target": b64(target), "exit_checks": [], "walk": False, "polish": False}
    paper.update(global_match=False, rescue=False, robust_icp=False, agent_points=PAPER_AGENT_POINTS)
    full = http.post("/register", json=paper).json()
    assert full["exit_checks"] == [] and len(full["trajectory"]) == 60  # the paper's PRANet-v2
    assert rotation_error_deg(np.array(full["rotation"]), T_gt[:3, :3]) < 0.05


def test_rescue_recovers_what_a_narrow_icp_misses(http: httpx.Client) -> None:
    """No agent steps (and no global match) and 20° and a 0.9 offset: ICP in its windows of a few spacings goes astray;
    the wide-window rescue from the input pose lands on the truth and is kept because it is more confident."""
    from oracle_scorer import asymmetric_cloud

    source = asymmetric_cloud(np.random.default_rng(0), 3000)  # a surface: the confidence judges surfaces
    R = Rotation.from_rotvec(np.deg2rad(20.0) * np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)).as_matrix()
    t = np.array([0.9, -0.45, 0.225])
    target = source @ R.T + t
    body = {"source": b64(source), "target": b64(target), "steps": [0, 0], "global_match": False}
    plain = http.post("/register", json={**body, "rescue": False}).json()
    assert plain["status"] == "suspect" and rotation_error_deg(np.array(plain["rotation"]), R) > 5.0
    rescued = http.post("/register", json=body).json()
    assert rescued["rescued"] == "wide_icp" and rescued["status"] == "converged"
    assert rotation_error_deg(np.array(rescued["rotation"]), R) < 0.05
    assert_allclose(rescued["translation"], t, atol=1e-3)


def test_timings_are_milliseconds_that_add_up(http: httpx.Client) -> None:
    """timing_ms is in milliseconds: the server's total lies within what the client waited, every stage is >= 0,
    and the stages between decoding and the response account for the total."""
    import time

    source, target, _ = synthetic_pair(n=400)
    t0 = time.perf_counter()
    r = http.post("/register", json={"source": b64(source), "target": b64(target)})
    client_ms = (time.perf_counter() - t0) * 1e3
    t = r.json()["timing_ms"]
    assert all(v >= 0.0 for v in t.values()), t
    assert 1.0 < t["total"] <= client_ms, (t, client_ms)
    stages = ("decode", "preprocess", "target_embedding", "agent_steps", "icp", "confidence", "rescue")
    assert sum(t[k] for k in stages) == pytest.approx(t["total"], rel=0.1, abs=2.0), t
    assert t["queue"] < client_ms
