"""A real ``pranet-serve`` process on a free loopback port, for tests that talk HTTP to the service.

Imported by name (pytest puts ``tests/`` on ``sys.path`` through its conftest). The process gets a
clean environment: the developer's own ``PRANET_*`` settings never leak in; pass what a test needs.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import httpx

START_TIMEOUT_S = 120.0


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def console_script(name: str) -> str:
    """The console script ``name`` installed beside this interpreter (else the one on PATH)."""
    beside = Path(sys.executable).parent / name
    found = str(beside) if beside.exists() else shutil.which(name)
    if found is None:
        raise RuntimeError(f"console script {name} not installed: pip install -e '.[dev]'")
    return found


def clean_env(settings: Mapping[str, str] | None = None) -> dict[str, str]:
    """This process's environment without ``PRANET_*`` (``PRANET_DATA_DIR`` kept), plus ``settings``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PRANET_") or k == "PRANET_DATA_DIR"}
    env.update(settings or {})
    return env


@dataclass
class LiveServer:
    url: str
    process: subprocess.Popen
    log: Path

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def terminate(self) -> None:
        """SIGTERM: uvicorn stops accepting, lets in-flight requests finish, then exits."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)

    def stop(self, timeout: float = 30.0) -> int:
        self.terminate()
        try:
            return self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            return self.process.wait(timeout=10)


def start_live_server(log_dir: Path, settings: Mapping[str, str] | None = None, args: Sequence[str] = ()) -> LiveServer:
    """Start ``pranet-serve --host 127.0.0.1 --port <free> *args`` with ``PRANET_*`` ``settings``; wait for /health."""
    for _attempt in range(3):  # the free port may be taken between probe and bind
        port = free_port()
        log = log_dir / f"pranet-serve-{port}.log"
        cmd = [console_script("pranet-serve"), "--host", "127.0.0.1", "--port", str(port), *args]
        with open(log, "wb") as out:
            process = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=clean_env(settings))
        server = LiveServer(f"http://127.0.0.1:{port}", process, log)
        deadline = time.monotonic() + START_TIMEOUT_S
        while process.poll() is None and time.monotonic() < deadline:
            try:
                if httpx.get(f"{server.url}/health", timeout=2.0).status_code == 200:
                    return server
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        code = server.stop()
        if "address already in use" not in server.output().lower():
            raise RuntimeError(f"pranet-serve did not come up (exit {code}):\n{server.output()[-3000:]}")
    raise RuntimeError("pranet-serve: no free port after 3 attempts")
