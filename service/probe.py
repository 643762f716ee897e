"""``python -m pranet.service.probe [ready|health]``: exit status 0 when the service in this container answers 200.

For the health checks of containers: the image's HEALTHCHECK, compose, Kubernetes' readiness probe. ``/ready``
needs the API key when one is set, and an HTTP probe cannot take it from a Secret; this reads ``PRANET_API_KEY``
and ``PRANET_PORT`` from the environment the service was started with. Standard library only: a fresh
interpreter runs it every few seconds.
"""

from __future__ import annotations

import os
import sys
import urllib.error
import urllib.request
from collections.abc import Sequence

PATHS = {"ready": "/ready", "health": "/health"}
TIMEOUT_S = 4.0


def probe(path: str, port: str, api_key: str | None) -> str | None:
    """None when ``GET 127.0.0.1:port/path`` answers 200, else why not."""
    headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
    request = urllib.request.Request(f"http://127.0.0.1:{port}{path}", headers=headers)
    try:
        with urllib.request.urlopen(request, timeout=TIMEOUT_S) as response:
            return None if response.status == 200 else f"HTTP {response.status}"
    except urllib.error.HTTPError as e:
        return f"HTTP {e.code}"
    except (urllib.error.URLError, OSError) as e:
        return str(getattr(e, "reason", e))


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    check = args[0] if args else "ready"
    if check not in PATHS or len(args) > 1:
        print(f"usage: python -m pranet.service.probe [{'|'.join(PATHS)}]", file=sys.stderr)
        return 2
    port = os.environ.get("PRANET_PORT", "8000")
    failure = probe(PATHS[check], port, os.environ.get("PRANET_API_KEY", "").strip() or None)
    if failure:
        print(f"pranet probe {check}: {failure} (127.0.0.1:{port})", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
