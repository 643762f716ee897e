#!/usr/bin/env bash
# The Docker image's install path, checked without Docker:
#   wheel of the working tree -> fresh venv with the service extra only, pinned by requirements/service.lock
#   -> torch absent -> pranet-serve started outside the repository (no repo source on sys.path)
#   -> registrations over HTTP (python's urllib, nothing else) -> pranet-client register-many (the batch Job's
#   command, from the same venv) -> SIGTERM.
# Usage: scripts/check_install_path.sh            (PYTHON=python3.11 to choose the interpreter)
set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PYTHON="${PYTHON:-python3}"
WORK="$(mktemp -d "${TMPDIR:-/tmp}/pranet-install-path.XXXXXX")"
SERVER_PID=""

cleanup() {
    if [[ -n "$SERVER_PID" ]] && kill -0 "$SERVER_PID" 2>/dev/null; then
        kill -TERM "$SERVER_PID" 2>/dev/null || true
        wait "$SERVER_PID" 2>/dev/null || true
    fi
    rm -rf "$WORK"
}
trap cleanup EXIT

say() { echo "[install-path] $*"; }

# 1. The wheel, built from a copy of the working tree (tracked and untracked, not ignored files), so that
#    no stale build/ folder of the checkout can leak into it.
say "building the wheel"
mkdir -p "$WORK/src" "$WORK/dist"
(cd "$REPO" && git ls-files -z --cached --others --exclude-standard | while IFS= read -r -d '' f; do
    [[ -e "$f" ]] && printf '%s\0' "$f"
done | tar --null -T - -cf -) | tar -xf - -C "$WORK/src"
"$PYTHON" -m pip wheel --quiet --no-deps "$WORK/src" -w "$WORK/dist" 2> >(grep -v -e "WARNING: Location" >&2)
WHEEL="$(ls "$WORK"/dist/pranet-*.whl)"
say "wheel: $(basename "$WHEEL")"

# 2. A fresh venv with the service extra only, and httpx for pranet-client, every dependency pinned (as the image).
say "installing the wheel with the service extra (and httpx) into a fresh venv"
"$PYTHON" -m venv "$WORK/venv"
"$WORK/venv/bin/pip" install --quiet -c "$REPO/requirements/service.lock" "${WHEEL}[service]" httpx \
    2> >(grep -v -e "WARNING: Location" >&2)

mkdir -p "$WORK/run"
cd "$WORK/run"  # outside the repository: only the installed package can be imported
"$WORK/venv/bin/python" - "$REPO" <<'PY'
import importlib.util
import sys

repo = sys.argv[1]
assert importlib.util.find_spec("torch") is None, "torch is installed in the service venv"
import pranet.engine.runtime
import pranet.service.app

for module in (pranet.engine.runtime, pranet.service.app):
    assert not module.__file__.startswith(repo), f"{module.__name__} imported from the repository: {module.__file__}"
print("[install-path] torch absent; pranet imported from", pranet.service.app.__file__)
PY

# 3. pranet-serve from that venv, on a free loopback port.
PORT="$("$WORK/venv/bin/python" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')"
say "starting pranet-serve on 127.0.0.1:$PORT"
env -u PRANET_API_KEY -u PRANET_MODEL_DIR PRANET_THREADS=1 \
    "$WORK/venv/bin/pranet-serve" --host 127.0.0.1 --port "$PORT" > "$WORK/serve.log" 2>&1 &
SERVER_PID=$!

# 4. Wait for /ready, then register two pairs over HTTP with a known T_target_source.
if ! "$WORK/venv/bin/python" - "http://127.0.0.1:$PORT" <<'PY'
import base64
import json
import sys
import time
import urllib.error
import urllib.request

import numpy as np

url = sys.argv[1]


def call(path, body=None, timeout=120):
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url + path, data=data, headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=timeout) as r:
        return json.loads(r.read())


deadline = time.monotonic() + 120
while True:
    try:
        ready = call("/ready", timeout=5)
        break
    except (urllib.error.URLError, ConnectionError, OSError):
        if time.monotonic() > deadline:
            sys.exit("[install-path] pranet-serve not ready after 120 s")
        time.sleep(0.5)
print("[install-path] ready:", json.dumps(ready["model"]))

# A random solid and a known motion: target = R @ source + t.
rng = np.random.default_rng(0)
source = rng.uniform(-1, 1, size=(6000, 3)) * [1.0, 0.6, 0.3]
angle = np.radians(8.0)
R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
t = np.array([0.05, -0.02, 0.03])
target = source @ R.T + t


def b64(p):
    return {"encoding": "base64-float32-le", "data": base64.b64encode(p.astype("<f4").tobytes()).decode()}


# (a) The full pipeline (agent + ICP) with the shipped model, compact encoding: a well-formed answer.
full = call("/register", {"source": b64(source), "target": b64(target), "icp": True})
T = np.asarray(full["transform"])
assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1]), full["transform"]
assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6), "not a rotation"
assert full["icp"]["applied"] and len(full["trajectory"]) > 0
assert full["model"]["sha256"] == ready["model"]["sha256"]
print(f"[install-path] full pipeline: {len(full['trajectory'])} steps, {full['timing_ms']['total']:.0f} ms")

# (b) ICP only (agent skipped), JSON lists: recovers the known T_target_source.
icp = call("/register", {"source": source[:2000].tolist(), "target": target[:2000].tolist(), "steps": [0, 0]})
T = np.asarray(icp["transform"])
rot_err = np.degrees(np.arccos(np.clip((np.trace(R.T @ T[:3, :3]) - 1) / 2, -1, 1)))
trans_err = np.linalg.norm(T[:3, 3] - t)
print(f"[install-path] ICP only: {rot_err:.3f} deg, {trans_err:.4f} translation error")
assert rot_err < 1.0 and trans_err < 0.01, icp["transform"]
assert icp["status"] == "converged" and 0.0 <= icp["confidence"] <= 1.0, (icp["status"], icp["confidence"])

# (c) The web viewer's page and files come from the wheel's package data.
for path in ("/", "/static/app.js", "/static/parsers.js", "/static/style.css", "/static/vendor/three.min.js"):
    with urllib.request.urlopen(url + path, timeout=30) as r:
        assert r.status == 200 and len(r.read()) > 100, path
print("[install-path] web viewer served from the wheel")

# (d) The OpenAPI page's Swagger UI comes from the installed fastapi-offline, not from a CDN.
with urllib.request.urlopen(url + "/docs", timeout=30) as r:
    page = r.read().decode()
assert "https://" not in page and "http://" not in page, "/docs names a remote asset"
with urllib.request.urlopen(url + "/static-offline-docs/swagger-ui-bundle.js", timeout=30) as r:
    assert r.status == 200 and len(r.read()) > 100_000
print("[install-path] /docs assets served locally")
PY
then
    say "FAILED; pranet-serve log:"
    tail -n 50 "$WORK/serve.log" >&2
    exit 1
fi

# 5. The batch client, as deploy/k8s/batch runs it from the image: the example pair, shard 0 of 1.
say "pranet-client register-many on examples/bunny"
printf 'id,source,target\nbunny,%s,%s\n' "$REPO/examples/bunny/bun045.ply" "$REPO/examples/bunny/bun000.ply" \
    > "$WORK/pairs.csv"
"$WORK/venv/bin/pranet-client" register-many "$WORK/pairs.csv" --out "$WORK/results.jsonl" \
    --shard-index 0 --shard-count 1 --quiet --url "http://127.0.0.1:$PORT"
"$WORK/venv/bin/python" - "$WORK/results.jsonl" <<'PY'
import json
import sys

lines = [json.loads(line) for line in open(sys.argv[1])]
assert len(lines) == 1 and lines[0]["id"] == "bunny" and "error" not in lines[0], lines
assert len(lines[0]["transform"]) == 4, lines[0]
print("[install-path] register-many:", lines[0]["status"])
PY
# The containers' health check (HEALTHCHECK, compose, the Kubernetes readiness probe) ships in the wheel.
PRANET_PORT="$PORT" "$WORK/venv/bin/python" -m pranet.service.probe ready
say "probe ready: OK"

# 6. Graceful stop.
kill -TERM "$SERVER_PID"
wait "$SERVER_PID" || true
SERVER_PID=""
say "OK"
