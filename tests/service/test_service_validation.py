"""One test per class of bad input: each gets a 4xx with a message that says what is wrong, never a 5xx.

The shared live server runs with ``PRANET_MAX_POINTS=20000`` and ``PRANET_MAX_BODY_BYTES=2000000``.
"""

from __future__ import annotations

import base64
import json
import socket
from urllib.parse import urlsplit

import httpx
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from service_helpers import b64, flat_shape, rotation_error_deg, synthetic_pair

MAX_POINTS = 20000
MAX_BODY = 2_000_000


def _good() -> tuple[list, list]:
    source, target, _ = synthetic_pair(n=50)
    return source.tolist(), target.tolist()


def _post(http: httpx.Client, **fields) -> httpx.Response:
    source, target = _good()
    body = {"source": source, "target": target, "steps": [0, 1], **fields}
    return http.post("/register", json=body)


def _messages(response: httpx.Response) -> str:
    """All of a 4xx's message text, for matching; asserts the error has the service's shape."""
    assert 400 <= response.status_code < 500, (response.status_code, response.text)
    detail = response.json()["detail"]
    assert "Traceback" not in response.text
    if isinstance(detail, str):
        return detail
    return " | ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in detail)


def _with_raw_value(raw: str) -> str:
    """A request body whose source[3][1] is the JSON text ``raw`` (which json.dumps would not write)."""
    source, target = _good()
    source[3][1] = "__RAW__"
    return json.dumps({"source": source, "target": target}).replace('"__RAW__"', raw)


@pytest.mark.parametrize("raw", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_nan_and_inf_in_a_list_are_refused(http: httpx.Client, raw: str) -> None:
    r = http.post("/register", content=_with_raw_value(raw), headers={"content-type": "application/json"})
    assert r.status_code == 422
    assert "source.list.3.1" in _messages(r) and "finite number" in _messages(r)


def test_nan_and_inf_in_base64_are_refused(http: httpx.Client) -> None:
    source, target, _ = synthetic_pair(n=50)
    for bad in (np.nan, np.inf):
        broken = source.copy()
        broken[7, 1] = bad
        r = http.post("/register", json={"source": b64(source), "target": b64(broken)})
        assert r.status_code == 422
        assert _messages(r) == "target: contains NaN or infinite values"


@pytest.mark.parametrize(
    "points", [[], [[0.0, 0.0, 1.0]], [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0, 1, 0]]]
)
def test_fewer_than_four_points(http: httpx.Client, points: list) -> None:
    """Three points always lie in a plane: the schema's minimum is 4, in both encodings."""
    r = _post(http, source=points)
    assert r.status_code == 422
    assert "at least 4 items" in _messages(r) and "source" in _messages(r)
    r = http.post("/register", json={"source": b64(np.array(points).reshape(-1, 3)), "target": _good()[1]})
    assert r.status_code == 422
    assert f"source: needs at least 4 points (3 always lie in a plane), got {len(points)}" == _messages(r)


@pytest.mark.parametrize(
    "cloud",
    [
        [[0.0, 1.0], [1.0, 2.0], [2.0, 3.0]],  # 2 per point
        [[0.0, 1.0, 2.0, 3.0]] * 3,  # 4 per point
        [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0],  # flat
        [[[0.0, 1.0, 2.0]]] * 3,  # one level too deep
        {"x": [1, 2, 3]},  # an object that is no encoded cloud
        "1 2 3",
    ],
)
def test_wrong_shape(http: httpx.Client, cloud) -> None:
    r = _post(http, target=cloud)
    assert r.status_code == 422
    assert "target" in _messages(r)


def test_base64_that_is_no_whole_number_of_points(http: httpx.Client) -> None:
    data = base64.b64encode(np.zeros(10, dtype="<f4").tobytes()).decode()  # 40 bytes: 3 1/3 points
    r = _post(http, source={"encoding": "base64-float32-le", "data": data})
    assert r.status_code == 422
    assert "not a whole number of float32 (x, y, z) points" in _messages(r)


@pytest.mark.parametrize(
    "data",
    ["AAAA*AAA", "AAAAA", "AAAAAAAAAAAAAAAA==="],
)
def test_invalid_base64(http: httpx.Client, data: str) -> None:
    r = _post(http, source={"encoding": "base64-float32-le", "data": data})
    assert r.status_code == 422
    assert "source" in _messages(r)


def test_unknown_encoding(http: httpx.Client) -> None:
    r = _post(http, source={"encoding": "base64-float64-le", "data": ""})
    assert r.status_code == 422
    assert "base64-float32-le" in _messages(r)


@pytest.mark.parametrize(
    ("points", "reason"),
    [
        ([[1.0, 2.0, 3.0]] * 10, "identical"),
        ([[float(i), 2.0 * i, -i] for i in range(10)], "collinear"),
    ],
)
def test_degenerate_clouds(http: httpx.Client, points: list, reason: str) -> None:
    for encode in (lambda p: p, lambda p: b64(np.array(p))):
        r = _post(http, source=encode(points))
        assert r.status_code == 422
        assert _messages(r).startswith("source: ") and reason in _messages(r)


def test_a_flat_cloud_is_registered_not_refused(http: httpx.Client) -> None:
    """A flat outline (a door, a leaf) turned out of its plane: its rotation is determined, so the default request
    answers it, to the truth (the same points in another order) and ``converged``, where ICP that trusted its
    normals would slide within the plane."""
    tilt = Rotation.from_rotvec([0.7, -0.4, 0.3]).as_matrix()
    source = flat_shape(seed=0) @ tilt.T
    R = Rotation.from_rotvec(np.deg2rad(30.0) * np.array([1.0, -2.0, 1.5]) / np.linalg.norm([1.0, -2.0, 1.5]))
    t = np.array([0.1, -0.05, 0.08])
    target = (source @ R.as_matrix().T + t)[np.random.default_rng(0).permutation(len(source))]
    r = http.post("/register", json={"source": b64(source), "target": b64(target)})
    assert r.status_code == 200, r.text
    body = r.json()
    T = np.asarray(body["transform"])
    assert rotation_error_deg(T[:3, :3], R.as_matrix()) < 0.1 and np.linalg.norm(T[:3, 3] - t) < 1e-3
    assert body["status"] == "converged"


@pytest.mark.parametrize("raw", ['"1.0"', "true", "null", '"x"', "[1]", "{}"])
def test_non_numeric_coordinates(http: httpx.Client, raw: str) -> None:
    r = http.post("/register", content=_with_raw_value(raw), headers={"content-type": "application/json"})
    assert r.status_code == 422
    assert "source.list.3.1: Input should be a valid number" in _messages(r)


def test_coordinates_beyond_the_documented_range(http: httpx.Client) -> None:
    source, target = _good()
    r = _post(http, source=[[1e300, 0.0, 0.0], *source])
    assert r.status_code == 422
    assert "less than or equal to 1000000000" in _messages(r)
    huge = np.array(source) * 1e30
    r = http.post("/register", json={"source": b64(huge), "target": target})
    assert r.status_code == 422
    assert "|x| <= 1e+09" in _messages(r)


def test_payload_too_large_by_content_length(http: httpx.Client) -> None:
    r = http.post("/register", content=b"x" * (MAX_BODY + 1), headers={"content-type": "application/json"})
    assert r.status_code == 413
    assert f"larger than this server's limit of {MAX_BODY:,} bytes" in _messages(r)


def test_payload_too_large_without_content_length(http: httpx.Client) -> None:
    """A chunked body has no Content-Length: the limit holds while it is read."""

    def chunks():
        for _ in range(MAX_BODY // 65536 + 2):
            yield b" " * 65536

    r = http.post("/register", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413
    assert f"larger than this server's limit of {MAX_BODY:,} bytes" in _messages(r)


def test_lying_content_length_is_refused_before_the_body(server_url: str) -> None:
    """A huge declared length is refused from the header alone (nothing of the body is sent)."""
    parts = urlsplit(server_url)
    with socket.create_connection((parts.hostname, parts.port), timeout=10) as s:
        s.sendall(
            b"POST /register HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            b"Content-Length: 99999999999\r\n\r\n"
        )
        head = s.recv(4096).decode(errors="replace")
    assert head.startswith("HTTP/1.1 413"), head


def test_too_many_points(http: httpx.Client) -> None:
    rng = np.random.default_rng(0)
    many = rng.normal(size=(MAX_POINTS + 1, 3))  # ~240 kB as base64: under the body limit
    r = http.post("/register", json={"source": b64(many), "target": b64(many[:100])})
    assert r.status_code == 413
    assert _messages(r) == (
        f"source: {MAX_POINTS + 1:,} points, more than this server's limit of {MAX_POINTS:,} (PRANET_MAX_POINTS); "
        "downsample the cloud or raise the limit"
    )
    as_list = np.round(many[: MAX_POINTS + 1], 1).tolist()
    body = json.dumps({"source": as_list[:100], "target": as_list}, separators=(",", ":"))
    assert len(body) < MAX_BODY
    r = http.post("/register", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 413
    assert _messages(r).startswith(
        f"target: {MAX_POINTS + 1:,} points as a JSON list, more than this server's limit of {MAX_POINTS:,} "
        "(PRANET_MAX_POINTS); send it base64-encoded"
    )


@pytest.mark.parametrize(
    "extra",
    [{"colour": "red"}, {"source_normals": []}, {"icp_threshold": 0.1}],
)
def test_unknown_top_level_fields(http: httpx.Client, extra: dict) -> None:
    r = _post(http, **extra)
    assert r.status_code == 422
    name = next(iter(extra))
    assert name in _messages(r) and "Extra inputs are not permitted" in _messages(r)


def test_unknown_field_in_an_encoded_cloud(http: httpx.Client) -> None:
    source, _, _ = synthetic_pair(n=50)
    r = _post(http, source={**b64(source), "dtype": "float32"})
    assert r.status_code == 422
    assert "dtype" in _messages(r)


@pytest.mark.parametrize(
    "fields",
    [
        {"steps": [201, 0]},
        {"steps": [-1, 3]},
        {"steps": []},
        {"steps": [1.5, 2]},
        {"seed": -1},
        {"seed": 2**40},
        {"policy": "random"},
        {"icp": "yes please"},
        {"return_trajectory": 3},
    ],
)
def test_out_of_range_options(http: httpx.Client, fields: dict) -> None:
    r = _post(http, **fields)
    assert r.status_code == 422
    assert next(iter(fields)) in _messages(r)


@pytest.mark.parametrize(
    "fields",
    [
        {"icp": 0},
        {"early_stop": "true"},
        {"return_trajectory": "yes"},
        {"seed": "5"},
        {"seed": 5.5},  # 5.0 is taken: JSON Schema's "integer" includes it
        {"steps": ["1", "2"]},
    ],
)
def test_no_type_coercion(http: httpx.Client, fields: dict) -> None:
    """Strict types: a client bug like sending "5" for 5 or 0 for false is reported, not guessed at."""
    r = _post(http, **fields)
    assert r.status_code == 422
    assert next(iter(fields)) in _messages(r)


@pytest.mark.parametrize("content_type", [None, "text/plain", "application/x-www-form-urlencoded", "application/xml"])
def test_wrong_content_type(http: httpx.Client, content_type: str | None) -> None:
    source, target = _good()
    headers = {"content-type": content_type} if content_type else {}
    r = http.post("/register", content=json.dumps({"source": source, "target": target}), headers=headers)
    assert r.status_code == 415
    assert "application/json" in _messages(r)


@pytest.mark.parametrize(
    "body",
    [b"", b"{", b"[]", b"null", b'{"source": [[0,0,0]],', b"{'source': 1}", b"\xff\xfe\x00", b"[" * 5000],
)
def test_malformed_json(http: httpx.Client, body: bytes) -> None:
    r = http.post("/register", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 422
    _messages(r)


def test_missing_clouds(http: httpx.Client) -> None:
    r = http.post("/register", json={"source": _good()[0]})
    assert r.status_code == 422
    assert "target: Field required" in _messages(r)


def test_wrong_method(http: httpx.Client) -> None:
    assert http.get("/register").status_code == 405
    assert http.post("/health").status_code == 405


def test_far_too_many_encoded_points_are_refused_before_decoding(http: httpx.Client) -> None:
    """The base64 length alone gives the points: over the limit, the cloud is not decoded, so its data need not
    even be valid float32 (here: base64 of a length no cloud has, 13 bytes a "point")."""
    n = MAX_POINTS + 5000
    junk = {"encoding": "base64-float32-le", "data": base64.b64encode(b"\x01" * (12 * n + 1)).decode()}
    r = http.post("/register", json={"source": b64(np.eye(4)[:, :3]), "target": junk})
    assert r.status_code == 413
    assert _messages(r).startswith(f"target: {n:,} points, more than this server's limit of {MAX_POINTS:,}")
