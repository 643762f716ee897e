"""Fixtures of the client tests: canned service responses on a real loopback HTTP server, and a real
``pranet-serve`` subprocess for the end-to-end tests."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import pytest
from client_helpers import start_server
from live_server import LiveServer


@dataclass
class FakeService:
    """A loopback HTTP server answering from ``routes``; records every request it gets."""

    url: str
    routes: dict[tuple[str, str], Callable[[dict[str, Any] | None], tuple[int, Any]]]
    requests: list[dict[str, Any]] = field(default_factory=list)


@pytest.fixture
def fake_service() -> Iterator[FakeService]:
    service = FakeService(url="", routes={})

    class Handler(BaseHTTPRequestHandler):
        def _answer(self, method: str) -> None:
            length = int(self.headers.get("Content-Length") or 0)
            raw = self.rfile.read(length) if length else b""
            body = json.loads(raw) if raw else None
            service.requests.append({"method": method, "path": self.path, "headers": dict(self.headers), "json": body})
            handler = service.routes.get((method, self.path))
            status, payload = handler(body) if handler else (404, {"detail": "Not Found"})
            data = payload.encode() if isinstance(payload, str) else json.dumps(payload).encode()
            self.send_response(status)
            self.send_header("Content-Type", "text/plain" if isinstance(payload, str) else "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def do_GET(self) -> None:  # noqa: N802 - http.server's naming
            self._answer("GET")

        def do_POST(self) -> None:  # noqa: N802
            self._answer("POST")

        def log_message(self, *args: Any) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    service.url = f"http://127.0.0.1:{server.server_address[1]}"
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield service
    finally:
        server.shutdown()
        server.server_close()


@pytest.fixture(scope="session")
def pranet_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    """A real ``pranet-serve`` with the shipped model, shared by the end-to-end tests."""
    server = start_server(tmp_path_factory.mktemp("server"))
    try:
        yield server
    finally:
        server.stop()
