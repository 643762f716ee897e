"""The wire encoding of a point cloud: ``{"encoding": "base64-float32-le", "data": <base64>}``.

``N * 3`` little-endian float32 values ``x0 y0 z0 x1 y1 z1 ...`` (row-major ``(N, 3)``), standard base64 with
padding (RFC 4648). The one definition used by the service, the client, ``pranet-bench`` and the load test.
"""

from __future__ import annotations

import base64
import binascii

import numpy as np
import numpy.typing as npt

ENCODING = "base64-float32-le"
BYTES_PER_POINT = 12


class WireError(ValueError):
    """Data that is not a valid encoded cloud (the message says why)."""


def encode_cloud(points: npt.ArrayLike) -> dict[str, str]:
    """``points: (N, 3)`` -> the compact JSON form (float32: about 7 significant digits)."""
    data = np.ascontiguousarray(np.asarray(points).reshape(-1, 3), dtype="<f4").tobytes()
    return {"encoding": ENCODING, "data": base64.b64encode(data).decode("ascii")}


def encoded_length(n_points: int) -> int:
    """Characters of ``data`` for ``n_points`` points: base64 writes 4 characters per 3 bytes, so 16 per point."""
    return 4 * -(-BYTES_PER_POINT * n_points // 3)


def point_count(data: str) -> int:
    """The points ``data`` decodes to (rounded down; exact when it is valid), without decoding it."""
    padding = 2 if data.endswith("==") else 1 if data.endswith("=") else 0
    return max(0, len(data) // 4 * 3 - padding) // BYTES_PER_POINT


def decode_cloud(data: str) -> np.ndarray:
    """The base64 ``data`` -> ``(N, 3)`` float64; raises ``WireError`` for invalid base64 or a partial point."""
    try:
        raw = base64.b64decode(data, validate=True)
    except (binascii.Error, ValueError) as e:
        raise WireError(f"invalid base64 ({e})") from None
    if len(raw) % BYTES_PER_POINT:
        raise WireError(
            f"{len(raw)} bytes is not a whole number of float32 (x, y, z) points ({BYTES_PER_POINT} bytes each)"
        )
    return np.frombuffer(raw, dtype="<f4").reshape(-1, 3).astype(np.float64)
