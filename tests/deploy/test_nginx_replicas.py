"""Replicas behind nginx with real parts: two ``pranet-serve`` processes on loopback and Debian's nginx with the
shipped config (``deploy/nginx/pranet.conf.template``), loaded through nginx by ``scripts/replica_check.py``.

SIGTERM on a replica under load loses no request: it finishes what it has in flight, nginx sends the rest to the
live replica. SIGKILL loses none either: nginx retries what was in flight on the killed replica on the live one.
CI runs the short form (``PRANET_REPLICA_SECONDS``, default 8 s of load per run); ``python
scripts/replica_check.py`` prints the full table. With ``PRANET_REQUIRE_NGINX=1`` (CI) a missing nginx fails
instead of skipping. The compose file is checked against the same template and the service's limits.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
import yaml

from pranet.service.settings import Settings

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "scripts" / "replica_check.py"
COMPOSE = REPO / "deploy" / "compose.yaml"
TEMPLATE = REPO / "deploy" / "nginx" / "pranet.conf.template"
SECONDS = os.environ.get("PRANET_REPLICA_SECONDS", "8")


@pytest.fixture(scope="module")
def replica_check(request: pytest.FixtureRequest):
    """The script as a module (it imports scripts/loadtest.py by name, beside it)."""
    sys.path.insert(0, str(SCRIPT.parent))
    request.addfinalizer(lambda: sys.path.remove(str(SCRIPT.parent)))
    import replica_check

    return replica_check


@pytest.fixture(scope="module")
def nginx() -> str:
    found = shutil.which("nginx") or ("/usr/sbin/nginx" if os.access("/usr/sbin/nginx", os.X_OK) else None)
    if found is None:
        if os.environ.get("PRANET_REQUIRE_NGINX") == "1":
            pytest.fail("nginx is required here (PRANET_REQUIRE_NGINX=1): apt-get install -y nginx")
        pytest.skip("nginx not installed (Debian: apt-get install -y nginx)")
    return found


# --- the compose file and the template agree ------------------------------------------------------------------


def compose_services() -> dict:
    return yaml.safe_load(COMPOSE.read_text())["services"]


def test_compose_sets_every_placeholder_of_the_template(replica_check) -> None:
    env = compose_services()["nginx"]["environment"]
    placeholders = set(re.findall(r"\$\{(PRANET_\w+)\}", TEMPLATE.read_text()))
    assert placeholders == {"PRANET_LISTEN", "PRANET_UPSTREAM_SERVERS", "PRANET_MAX_BODY_BYTES"}
    assert placeholders <= set(env)
    assert re.match(env["NGINX_ENVSUBST_FILTER"], "PRANET_LISTEN")
    # The same server parameters as the tested config, for the one name Docker resolves to every replica.
    assert env["PRANET_UPSTREAM_SERVERS"] == replica_check.UPSTREAM_SERVER.format(address="pranet:8000")


def test_compose_body_limit_is_the_services(monkeypatch: pytest.MonkeyPatch) -> None:
    """nginx refuses exactly the bodies the replicas refuse: the limit they derive from their own settings."""
    services = compose_services()
    for key in [k for k in os.environ if k.startswith("PRANET_")]:
        monkeypatch.delenv(key)
    for key, value in services["pranet"]["environment"].items():
        if key.startswith("PRANET_") and "${" not in str(value):
            monkeypatch.setenv(key, str(value))
    assert int(services["nginx"]["environment"]["PRANET_MAX_BODY_BYTES"]) == Settings().body_limit_bytes


def test_compose_stop_grace_outlasts_the_graceful_shutdown() -> None:
    grace = compose_services()["pranet"]["stop_grace_period"]
    assert grace.endswith("s") and float(grace[:-1]) > Settings().shutdown_timeout_s


def test_template_refuses_a_missing_placeholder(replica_check) -> None:
    with pytest.raises(ValueError, match="PRANET_MAX_BODY_BYTES"):
        replica_check.render_template(TEMPLATE.read_text(), {"PRANET_LISTEN": "1", "PRANET_UPSTREAM_SERVERS": ""})


def test_nginx_accepts_the_compose_config(replica_check, nginx: str, tmp_path: Path) -> None:
    """``nginx -t`` on the template rendered with the compose values (the service's name, which only Docker's DNS
    knows, replaced by loopback)."""
    env = compose_services()["nginx"]["environment"]
    values = {k: str(v).replace("pranet:8000", "127.0.0.1:8000") for k, v in env.items()}
    (tmp_path / "site.conf").write_text(replica_check.render_template(TEMPLATE.read_text(), values))
    conf = tmp_path / "nginx.conf"
    conf.write_text(f"pid {tmp_path}/nginx.pid; events {{}} http {{ include {tmp_path}/site.conf; }}\n")
    done = subprocess.run(
        [nginx, "-t", "-p", str(tmp_path), "-c", str(conf), "-e", str(tmp_path / "error.log")],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert done.returncode == 0, done.stderr


def test_nginx_answers_in_the_services_shape_when_it_cannot(replica_check, nginx: str, tmp_path: Path) -> None:
    """No replica to answer: a JSON 503 with Retry-After, which pranet-client retries; a body over the service's
    limit, announced by Content-Length: a JSON 413 before the body is read."""
    with replica_check.nginx_up(tmp_path, [f"127.0.0.1:{replica_check.free_port()}"]) as proxy:
        r = httpx.post(f"{proxy.url}/register", content=b"{}", headers={"content-type": "application/json"})
        assert r.status_code == 503, r.text
        assert r.headers["retry-after"] == "1" and "retry later" in r.json()["detail"]

        limit = Settings().body_limit_bytes
        port = int(proxy.url.rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
            s.sendall(f"POST /register HTTP/1.1\r\nHost: x\r\nContent-Length: {limit + 1}\r\n\r\n".encode())
            head, _, body = s.recv(65536).partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 413"), head
        assert str(limit) in json.loads(body)["detail"]


# --- the topology under load -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def runs(nginx: str, tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict]:
    """``scripts/replica_check.py --runs term,kill``, the committed command behind docs/PERFORMANCE.md's table."""
    out = tmp_path_factory.mktemp("replicas") / "runs.json"
    cmd = [sys.executable, str(SCRIPT), "--runs", "term,kill", "--duration", SECONDS, "--points", "1000"]
    done = subprocess.run([*cmd, "--json", str(out)], capture_output=True, text=True, timeout=600)
    print(done.stdout)
    assert out.exists(), done.stdout + done.stderr[-3000:]
    return {r["run"]: r for r in json.loads(out.read_text())["runs"]}


def _both_replicas_served_before_the_signal(run: dict) -> None:
    answered_by = run["nginx"]["answered_by"]
    assert answered_by.get("replica0", 0) > 0 and answered_by.get("replica1", 0) > 0, answered_by
    assert run["before"]["answered"] > 0 and run["after"]["sent"] > 0, (run["before"], run["after"])


@pytest.mark.slow
def test_sigterm_loses_no_request(runs: dict[str, dict]) -> None:
    run = runs["term"]
    _both_replicas_served_before_the_signal(run)
    assert run["signal"]["in_flight"] >= 2, "too little in flight on the replica at the signal: the run proves little"
    assert run["all"]["failed"] == 0, (run["statuses"], run["errors"])
    assert run["all"]["answered"] == run["all"]["sent"] == run["nginx"]["requests"]
    # The replica answered what it had in flight after the signal (a replica that dropped it would leave nginx to
    # retry it elsewhere: no loss either, but no graceful shutdown), then exited on its own, within its grace period.
    assert run["nginx"]["answered_after_signal_by"].get("replica0", 0) >= 1, run["nginx"]
    assert run["signal"]["exit"] in (0, -15), run["signal"]
    assert run["signal"]["exit_s"] < Settings().shutdown_timeout_s
    # Every request sent after the signal was answered, by the live replica.
    assert run["after"]["answered"] == run["after"]["sent"]


@pytest.mark.slow
def test_sigkill_loses_nothing_nginx_retries_on_the_live_replica(runs: dict[str, dict]) -> None:
    run = runs["kill"]
    _both_replicas_served_before_the_signal(run)
    assert run["signal"]["in_flight"] >= 2 and run["signal"]["exit"] == -9, run["signal"]
    assert run["nginx"]["answered_after_signal_by"].get("replica0", 0) == 0, run["nginx"]
    # The killed replica's registrations in flight, and the next ones sent to it, were tried again on the live one
    # (proxy_next_upstream ... non_idempotent: without it, the POSTs in flight are lost with a 502).
    assert run["nginx"]["retried"] >= 1, run["nginx"]
    assert run["all"]["failed"] == 0, (run["statuses"], run["errors"])
