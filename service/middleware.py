"""Pure ASGI middlewares: API-key check and request-body limits (size, time). Both answer with JSON errors."""

from __future__ import annotations

import json
import secrets
from collections.abc import Iterable

import anyio
from starlette.types import ASGIApp, Message, Receive, Scope, Send


async def send_json(send: Send, status: int, detail: str, headers: Iterable[tuple[bytes, bytes]] = ()) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                *headers,
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


class ApiKeyMiddleware:
    """Every path but ``open_paths`` (exact) and those under ``open_prefixes`` needs ``Authorization: Bearer
    <key>``; else 401."""

    def __init__(
        self,
        app: ASGIApp,
        api_key: str,
        open_paths: Iterable[str] = ("/health",),
        open_prefixes: Iterable[str] = (),
    ):
        self.app = app
        self.expected = f"Bearer {api_key}".encode()
        self.open_paths = frozenset(open_paths)
        self.open_prefixes = tuple(open_prefixes)

    def _is_open(self, path: str) -> bool:
        # Everything under an open prefix is routed to its static-files mount (even "/static/../register"),
        # which serves only files inside its folder.
        return path in self.open_paths or (bool(self.open_prefixes) and path.startswith(self.open_prefixes))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or self._is_open(scope["path"]):
            await self.app(scope, receive, send)
            return
        given = dict(scope["headers"]).get(b"authorization", b"")
        if not secrets.compare_digest(given, self.expected):
            detail = "missing or invalid API key: send the header 'Authorization: Bearer <key>'"
            await send_json(send, 401, detail, [(b"www-authenticate", b"Bearer")])
            return
        await self.app(scope, receive, send)


# A refused body is not read: closing the connection spares the server draining what the client still sends
# (uvicorn would read and discard it to keep the connection alive), and the client learns at once.
CLOSE = [(b"connection", b"close")]


class _BodyRefused(Exception):
    def __init__(self, status: int, detail: str):
        self.status = status
        self.detail = detail


class BodyLimitsMiddleware:
    """Bounds what one request body may cost before the app parses it.

    - 413 for a body larger than ``max_bytes``: by its Content-Length before a byte of it is read, or (chunked,
      no Content-Length) as soon as the bytes read pass the limit;
    - 408 when the body has not arrived ``timeout_s`` after the request's headers: a slow client holds a
      registration slot (the route admits before it reads) for at most that long.

    ``hint`` ends the 413's message: what the limit is derived from and how to get under it.
    """

    def __init__(self, app: ASGIApp, max_bytes: int, timeout_s: float, hint: str = ""):
        self.app = app
        self.max_bytes = max_bytes
        self.timeout_s = timeout_s
        self.hint = hint

    def _too_large(self, size: str) -> _BodyRefused:
        detail = f"request body of {size} bytes is larger than this server's limit of {self.max_bytes:,} bytes"
        return _BodyRefused(413, f"{detail}{'; ' + self.hint if self.hint else ''}")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        length = dict(scope["headers"]).get(b"content-length")
        if length is not None:
            try:
                declared = int(length)
            except ValueError:
                await send_json(send, 400, "invalid Content-Length header")
                return
            if declared > self.max_bytes:
                refused = self._too_large(f"{declared:,}")
                await send_json(send, refused.status, refused.detail, CLOSE)
                return
        deadline = anyio.current_time() + self.timeout_s
        received = 0
        body_done = False
        started = False

        async def limited_receive() -> Message:
            nonlocal received, body_done
            if body_done:  # later receives only wait for a disconnect (streaming responses): no deadline
                return await receive()
            try:
                with anyio.fail_after(max(0.0, deadline - anyio.current_time())):
                    message = await receive()
            except TimeoutError:
                raise _BodyRefused(
                    408,
                    f"request body not received within {self.timeout_s:g} s ({received:,} bytes arrived); "
                    "send it faster, or smaller (base64-encoded clouds are 2-4x smaller than JSON lists)",
                ) from None
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise self._too_large(f"more than {received:,}")
                body_done = not message.get("more_body", False)
            else:
                body_done = True  # http.disconnect
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except _BodyRefused as refused:
            if started:
                raise
            await send_json(send, refused.status, refused.detail, CLOSE)
