"""The web viewer (``GET /``, ``service/static``): its file parsers in node, and the whole page in headless
Chromium against a real ``pranet-serve`` with an API key (``viewer.spec.mjs``, playwright-core); and the
OpenAPI page ``/docs`` rendered in Chromium with the network blocked beyond the service (``docs.spec.mjs``).

Needs node, ``npm ci`` in ``tests/web`` and Chromium (``apt-get install chromium``; ``$CHROMIUM`` to
use another binary); the tests skip, saying which is missing, otherwise, or fail when
``$PRANET_REQUIRE_BROWSER`` is set (CI sets it: a skipped browser test must not pass). The screenshot goes to
``$PRANET_VIEWER_SCREENSHOT`` (default ``tests/web/out/viewer.png``, git-ignored).
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import struct
import subprocess
from pathlib import Path

import httpx
import numpy as np
import pytest
from live_server import start_live_server

from pranet.client.io import read_point_cloud, write_point_cloud

WEB = Path(__file__).resolve().parent
REPO = WEB.parents[1]
CHROMIUM = os.environ.get("CHROMIUM", "/usr/bin/chromium")
SCREENSHOT = Path(os.environ.get("PRANET_VIEWER_SCREENSHOT") or WEB / "out" / "viewer.png")
API_KEY = "viewer-test-key"


def _missing(reason: str) -> None:
    """Skip, or fail where the browser test is required (``$PRANET_REQUIRE_BROWSER``, set by ``.ci/run``)."""
    if os.environ.get("PRANET_REQUIRE_BROWSER"):
        pytest.fail(f"browser test required but cannot run: {reason}")
    pytest.skip(reason)


def _node() -> str:
    node = shutil.which("node")
    if node is None:
        _missing("node is not installed (apt-get install nodejs)")
    if not (WEB / "node_modules" / "playwright-core").is_dir():
        _missing("tests/web/node_modules missing: run `npm ci` in tests/web")
    return node


def test_static_files_are_served_without_the_api_key(tmp_path_factory: pytest.TempPathFactory) -> None:
    """In-process: the page and its files are open, everything else still needs the key; no CDN."""
    from fastapi.testclient import TestClient

    from pranet.service.app import create_app
    from pranet.service.settings import Settings

    with TestClient(create_app(Settings(api_key=API_KEY))) as client:
        page = client.get("/")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        for path in ("/static/app.js", "/static/parsers.js", "/static/vendor/three.min.js"):
            r = client.get(path)
            assert r.status_code == 200 and "javascript" in r.headers["content-type"], path
        assert client.get("/static/style.css").status_code == 200
        assert client.get("/static/missing.js").status_code == 404
        assert client.get("/ready").status_code == 401
        assert client.post("/register", json={}).status_code == 401
        assert "/" not in client.get("/openapi.json", headers={"Authorization": f"Bearer {API_KEY}"}).json()["paths"]
    for name in ("index.html", "app.js", "parsers.js"):
        text = (REPO / "service" / "static" / name).read_text()
        assert "http://" not in text and "https://" not in text, f"{name} loads something from the network"


def _ply_float32_big_endian(path: Path, points: np.ndarray) -> None:
    header = (
        f"ply\nformat binary_big_endian 1.0\nelement vertex {len(points)}\nproperty float x\nproperty float y\n"
        "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    body = b"".join(struct.pack(">fffBBB", *p, 10, 20, 30) for p in points) + struct.pack(">Biii", 3, 0, 1, 2)
    path.write_bytes(header.encode() + body)


def _ply_ascii_face_first(path: Path, points: np.ndarray) -> None:
    lines = ["ply", "format ascii 1.0", "element face 1", "property list uchar int vertex_indices"]
    lines += [f"element vertex {len(points)}", "property float nx", "property double x", "property double y"]
    lines += ["property double z", "end_header", "3 0 1 2"]
    lines += [f"0.5 {float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in points]
    path.write_text("\n".join(lines) + "\n")


def test_parsers_in_node(tmp_path: Path) -> None:
    node = _node()
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3)) * [10.0, 1.0, 0.1] + [1000.0, -5.0, 0.0]
    f32 = pts.astype(np.float32).astype(np.float64)
    good: list[dict] = []

    def add(name: str, expected: np.ndarray | None = None, atol: float = 1e-9) -> None:
        """``expected``: default, what the Python client reads from the file (Open3D's own precision)."""
        expected = read_point_cloud(tmp_path / name) if expected is None else expected
        good.append({"name": name, "path": str(tmp_path / name), "points": expected.tolist(), "atol": atol})

    write_point_cloud(tmp_path / "binary.ply", pts)
    add("binary.ply", pts)
    write_point_cloud(tmp_path / "ascii.ply", pts, ascii=True)
    add("ascii.ply", atol=1e-6)
    _ply_float32_big_endian(tmp_path / "big_endian_colors_faces.ply", f32)
    add("big_endian_colors_faces.ply", f32, 1e-4)
    _ply_ascii_face_first(tmp_path / "faces_first.ply", pts)
    add("faces_first.ply", pts)
    write_point_cloud(tmp_path / "ascii.pcd", pts, ascii=True)
    add("ascii.pcd", atol=1e-6)
    write_point_cloud(tmp_path / "binary.pcd", pts)
    add("binary.pcd")
    np.savetxt(tmp_path / "cloud.xyz", pts, header="x y z")
    add("cloud.xyz", pts, 1e-6)
    np.save(tmp_path / "cloud.npy", pts.astype(np.float32))
    add("cloud.npy", f32)
    np.save(tmp_path / "cloud64.npy", pts)
    add("cloud64.npy", pts)
    bad = []
    for name, content, match in (
        ("not_a.ply", b"hello\nend_header\n1 2 3\n", "not a PLY"),
        (
            "short.ply",
            b"ply\nformat binary_little_endian 1.0\nelement vertex 9\nproperty float x\n"
            b"property float y\nproperty float z\nend_header\n\x00\x00",
            "shorter",
        ),
        ("two_columns.xyz", b"1 2\n3 4\n", "fewer than 3"),
        ("nan.xyz", b"1 2 3\n4 nan 6\n7 8 9\n", "not a number"),
        ("cloud.obj", b"v 1 2 3\n", "unsupported file type"),
        ("matrix.npy", None, "(N, 3)"),
    ):
        if content is None:
            np.save(tmp_path / name, np.zeros((4, 4), np.float32))
        else:
            (tmp_path / name).write_bytes(content)
        bad.append({"name": name, "path": str(tmp_path / name), "match": match})
    encoded = base64.b64encode(np.array([1, -2.5, 3, 0.25, 1e6, -7], dtype="<f4").tobytes()).decode()
    manifest = tmp_path / "manifest.json"
    manifest.write_text(json.dumps({"good": good, "bad": bad, "encoded": encoded}))
    proc = subprocess.run(
        [node, str(WEB / "parsers.test.mjs"), str(manifest)], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1])["ok"]


@pytest.fixture(scope="module")
def guarded_server(tmp_path_factory: pytest.TempPathFactory):
    server = start_live_server(
        tmp_path_factory.mktemp("viewer"),
        {"PRANET_API_KEY": API_KEY, "PRANET_THREADS": "1", "PRANET_LOG_LEVEL": "warning"},
    )
    yield server
    server.stop()


def test_viewer_registers_two_ply_files_in_chromium(guarded_server, tmp_path: Path) -> None:
    node = _node()
    if not Path(CHROMIUM).exists():
        _missing(f"Chromium not found at {CHROMIUM} (apt-get install chromium, or set $CHROMIUM)")
    assert httpx.get(f"{guarded_server.url}/").status_code == 200
    rng = np.random.default_rng(1)
    source = rng.normal(size=(1500, 3)) * [1.0, 0.5, 0.25]
    angle = np.deg2rad(5.0)
    R = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    target = source @ R.T + [0.05, -0.03, 0.02]
    write_point_cloud(tmp_path / "source.ply", source)  # binary little endian (Open3D)
    write_point_cloud(tmp_path / "target.ply", target, ascii=True)
    env = {
        **os.environ,
        "PRANET_VIEWER_URL": guarded_server.url,
        "PRANET_VIEWER_SOURCE": str(tmp_path / "source.ply"),
        "PRANET_VIEWER_TARGET": str(tmp_path / "target.ply"),
        "PRANET_VIEWER_API_KEY": API_KEY,
        "PRANET_VIEWER_STEPS": "0,2",  # a couple of agent steps, then ICP: converges with any model
        "PRANET_VIEWER_SCREENSHOT": str(SCREENSHOT),
        "CHROMIUM": CHROMIUM,
    }
    proc = subprocess.run(
        [node, str(WEB / "viewer.spec.mjs")], capture_output=True, text=True, timeout=180, env=env, cwd=REPO
    )
    lines = proc.stdout.strip().splitlines()
    report = json.loads(lines[-1]) if lines else {}
    assert proc.returncode == 0 and report.get("ok"), proc.stdout + proc.stderr
    assert report["loaded"] == [1500, 1500]
    assert report["status"] == "converged" and report["frames"] == 4  # input, 2 steps, after ICP
    assert SCREENSHOT.stat().st_size > 10_000
    print(f"viewer screenshot: {SCREENSHOT}")


def test_docs_page_renders_offline_in_chromium(guarded_server) -> None:
    """Swagger UI at /docs renders the /register operation from the service's own assets, with every other host
    blocked (before fastapi-offline, the page loaded its script from a CDN and stayed blank offline)."""
    node = _node()
    if not Path(CHROMIUM).exists():
        _missing(f"Chromium not found at {CHROMIUM} (apt-get install chromium, or set $CHROMIUM)")
    env = {
        **os.environ,
        "PRANET_DOCS_URL": guarded_server.url,
        "PRANET_DOCS_API_KEY": API_KEY,
        "PRANET_DOCS_SCREENSHOT": str(SCREENSHOT.parent / "docs.png"),
        "CHROMIUM": CHROMIUM,
    }
    proc = subprocess.run(
        [node, str(WEB / "docs.spec.mjs")], capture_output=True, text=True, timeout=120, env=env, cwd=REPO
    )
    lines = proc.stdout.strip().splitlines()
    report = json.loads(lines[-1]) if lines else {}
    assert proc.returncode == 0 and report.get("ok"), proc.stdout + proc.stderr
    assert "/register" in report["operations"] and report["blocked"] == []
    assert report["title"] and "PRANet" in report["title"]
