"""HTTP client of the PRANet registration service (``pranet-serve``).

    with PranetClient("http://127.0.0.1:8000") as client:
        result = client.register("bun045.ply", "bun000.ply")  # source, target
        result.transform  # (4, 4) T_target_source: target ≈ R @ source + t

Clouds are sent as JSON lists, or for more than ``compact_threshold`` points as
``{"encoding": "base64-float32-le", "data": ...}`` (little-endian float32, x y z per point),
which is about 4x smaller and 40x faster to parse. Large clouds must use it: a server takes at most
200,000 points per cloud as a JSON list (``PRANET_MAX_LIST_POINTS``) and 1,200,000 base64-encoded
(``PRANET_MAX_POINTS``), by default; past those it answers 413 (``PranetError``, ``status_code`` 413) with the
count and the fix: downsample the cloud.

Many pairs: ``client.register_many("pairs.csv", "results.jsonl", concurrency=4)`` (``pranet.client.batch``).
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import httpx
import numpy as np
import numpy.typing as npt

from pranet.client.io import read_point_cloud
from pranet.core import wire

if TYPE_CHECKING:
    from pranet.client.batch import BatchSummary, Pair

Array = npt.NDArray[np.float64]
CloudLike = npt.ArrayLike | str | os.PathLike[str]

DEFAULT_URL = "http://127.0.0.1:8000"
COMPACT_ENCODING = wire.ENCODING
DEFAULT_COMPACT_THRESHOLD = 5000  # points; larger clouds are sent base64-encoded


class PranetError(Exception):
    """The service answered with an error (4xx/5xx) or an unexpected body.

    ``status_code`` is the HTTP status (``None`` when there was no answer), ``detail`` the server's
    parsed error body when it had one, ``retry_after`` the seconds its ``Retry-After`` header asked for.
    """

    def __init__(
        self, message: str, status_code: int | None = None, detail: Any = None, retry_after: float | None = None
    ) -> None:
        super().__init__(message)
        self.message = message
        self.status_code = status_code
        self.detail = detail
        self.retry_after = retry_after


class PranetConnectionError(PranetError):
    """The service could not be reached, or did not answer in time."""


@dataclass
class TrajectoryStep:
    step: int
    action: str
    transform: Array  # (4, 4) T_target_source after this step (before ICP), world units


@dataclass
class RegistrationResult:
    """The service's answer to ``POST /register``; ``raw`` keeps the whole JSON body."""

    transform: Array  # (4, 4) T_target_source: target ≈ R @ source + t
    rotation: Array  # (3, 3)
    translation: Array  # (3,)
    trajectory: list[TrajectoryStep]
    icp: dict[str, Any] | None  # {"applied", "fitness", "inlier_rmse"}
    timing_ms: dict[str, float]
    model: dict[str, Any]
    confidence: float | None = None  # in [0, 1]: how tight the clouds' overlap is at their resolution (API docs)
    status: str | None = None  # "converged" | "suspect"
    matches: int = 0  # feature matches that certified a global match as converged (0: the confidence decided)
    initial_transform: Array | None = None  # (4, 4) the agent's start pose (the identity unless init="global")
    n_source: int | None = None  # points the service received
    n_target: int | None = None
    exit_checks: list[dict[str, Any]] = field(default_factory=list)  # [{"step", "confidence"}]: ICP checks run
    rescued: str | None = None  # "wide_icp" | "restarts" | "shifted_icp" | "global_starts" | "turned_icp", if any
    # which candidate won: "agent", "global_match", "restarts", "wide_icp", "shifted_icp", "global_starts", "turned_icp"
    candidate: str | None = None
    candidates: dict[str, float] = field(default_factory=dict)  # every candidate tried -> its best confidence
    spacing: float | None = None  # the data's resolution (median nearest-neighbour distance), input units
    network_calls: int | None = None  # source poses the reward network scored
    raw: dict[str, Any] = field(default_factory=dict, repr=False)

    @classmethod
    def from_json(cls, body: dict[str, Any]) -> RegistrationResult:
        try:
            T = np.asarray(body["transform"], dtype=np.float64)
            if T.shape != (4, 4):
                raise ValueError(f"transform has shape {T.shape}, expected (4, 4)")
            rotation = np.asarray(body.get("rotation", T[:3, :3]), dtype=np.float64).reshape(3, 3)
            translation = np.asarray(body.get("translation", T[:3, 3]), dtype=np.float64).reshape(3)
            trajectory = [
                TrajectoryStep(int(s["step"]), str(s["action"]), np.asarray(s["transform"], dtype=np.float64))
                for s in body.get("trajectory") or []
            ]
            start = body.get("initial_transform")
            initial = np.asarray(start, dtype=np.float64).reshape(4, 4) if start is not None else None
        except (KeyError, TypeError, ValueError) as e:
            raise PranetError(f"unexpected response from the service: {e}", detail=body) from e
        confidence = body.get("confidence")
        return cls(
            transform=T,
            rotation=rotation,
            translation=translation,
            trajectory=trajectory,
            icp=body.get("icp"),
            timing_ms=dict(body.get("timing_ms") or {}),
            model=dict(body.get("model") or {}),
            confidence=float(confidence) if confidence is not None else None,
            status=body.get("status"),
            matches=int(body.get("matches") or 0),
            initial_transform=initial,
            n_source=body.get("n_source"),
            n_target=body.get("n_target"),
            exit_checks=list(body.get("exit_checks") or []),
            rescued=body.get("rescued"),
            candidate=body.get("candidate"),
            candidates=dict(body.get("candidates") or {}),
            spacing=body.get("spacing"),
            network_calls=body.get("network_calls"),
            raw=body,
        )


def load_cloud(cloud: CloudLike) -> Array:
    """``cloud``: an ``(N, 3)`` array, or a path to a PLY/PCD/XYZ/NPY file -> ``(N, 3)`` float64."""
    if isinstance(cloud, (str, os.PathLike)):
        return read_point_cloud(cloud)
    points = np.asarray(cloud, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"expected points of shape (N, 3), got {points.shape}")
    return points


def encode_cloud(points: npt.ArrayLike, compact_threshold: int = DEFAULT_COMPACT_THRESHOLD) -> Any:
    """``points: (N, 3)`` -> the JSON value the service accepts.

    A list of ``[x, y, z]`` for ``N <= compact_threshold``, else
    ``{"encoding": "base64-float32-le", "data": base64(float32 little-endian, row-major)}``.
    """
    p = np.asarray(points, dtype=np.float64)
    return wire.encode_cloud(p) if len(p) > compact_threshold else p.tolist()


def _error_message(response: httpx.Response) -> tuple[str, Any]:
    """The server's own words for an error response, and the parsed body."""
    try:
        body = response.json()
    except ValueError:
        text = response.text.strip()
        return (text[:500] or response.reason_phrase), None
    detail = body.get("detail", body.get("error", body.get("message", body))) if isinstance(body, dict) else body
    if isinstance(detail, list):  # FastAPI validation errors: [{"loc": [...], "msg": ...}, ...]
        parts = []
        for item in detail:
            if isinstance(item, dict):
                loc = ".".join(str(x) for x in item.get("loc", ()) if x != "body")
                parts.append(f"{loc}: {item.get('msg', item)}" if loc else str(item.get("msg", item)))
            else:
                parts.append(str(item))
        return "; ".join(parts), body
    if isinstance(detail, dict):
        return str(detail.get("message", detail)), body
    return str(detail), body


def _retry_after(response: httpx.Response) -> float | None:
    """``Retry-After`` in seconds (the HTTP-date form is not used by the service and is ignored)."""
    try:
        return max(0.0, float(response.headers["retry-after"]))
    except (KeyError, ValueError):
        return None


class PranetClient:
    """Client of one service. ``api_key`` is sent as ``Authorization: Bearer <key>``.

    ``timeout`` (seconds) bounds each request; ``transport`` lets tests plug in ``httpx.MockTransport``.
    """

    def __init__(
        self,
        base_url: str = DEFAULT_URL,
        api_key: str | None = None,
        timeout: float = 120.0,
        compact_threshold: int = DEFAULT_COMPACT_THRESHOLD,
        transport: httpx.BaseTransport | None = None,
    ) -> None:
        self.base_url = base_url.rstrip("/")
        self.compact_threshold = compact_threshold
        headers = {"Accept": "application/json"}
        if api_key:
            headers["Authorization"] = f"Bearer {api_key}"
        self._http = httpx.Client(base_url=self.base_url, headers=headers, timeout=timeout, transport=transport)

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> PranetClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _request(self, method: str, path: str, **kwargs: Any) -> dict[str, Any]:
        try:
            response = self._http.request(method, path, **kwargs)
        except httpx.TimeoutException as e:
            raise PranetConnectionError(f"no answer from {self.base_url}{path} in time ({type(e).__name__})") from e
        except httpx.TransportError as e:
            raise PranetConnectionError(f"cannot reach the service at {self.base_url}: {e}") from e
        if response.status_code >= 400:
            message, body = _error_message(response)
            status = response.status_code
            raise PranetError(f"HTTP {status} from {path}: {message}", status, body, _retry_after(response))
        try:
            body = response.json()
        except ValueError as e:
            raise PranetError(f"{path} answered with a body that is not JSON", response.status_code) from e
        if not isinstance(body, dict):
            raise PranetError(f"{path} answered with a JSON {type(body).__name__}, expected an object", detail=body)
        return body

    def health(self) -> dict[str, Any]:
        """``GET /health``: the process is up."""
        return self._request("GET", "/health")

    def ready(self) -> dict[str, Any]:
        """``GET /ready``: the model is loaded; raises ``PranetError`` (status 503) while it is not."""
        return self._request("GET", "/ready")

    def model(self) -> dict[str, Any]:
        """``GET /model``: name, version and sha256 of the served model (and its card)."""
        return self._request("GET", "/model")

    def wait_ready(self, timeout: float = 60.0, interval: float = 0.25) -> dict[str, Any]:
        """Poll ``/ready`` until it answers 200 or ``timeout`` seconds pass (then re-raise the last error)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                return self.ready()
            except PranetError:
                if time.monotonic() >= deadline:
                    raise
            time.sleep(interval)

    def register(self, source: CloudLike, target: CloudLike, icp: bool = True, **options: Any) -> RegistrationResult:
        """Register ``source`` onto ``target``: arrays ``(N, 3)`` / ``(M, 3)`` or point cloud file paths.

        ``options`` are passed through to the service (``policy``, ``early_stop``, ``seed``, ``steps``,
        ``exit_checks``, ``rescue``, ``global_match``, ``walk``, ``fine_matching``, ``polish``, ``robust_icp``,
        ``return_trajectory``, ``init``, ``starts``); ``None`` values are left out so the server's defaults apply.
        """
        payload: dict[str, Any] = {
            "source": encode_cloud(load_cloud(source), self.compact_threshold),
            "target": encode_cloud(load_cloud(target), self.compact_threshold),
            "icp": bool(icp),
        }
        payload.update({k: v for k, v in options.items() if v is not None})
        return RegistrationResult.from_json(self._request("POST", "/register", json=payload))

    def register_many(
        self,
        pairs: str | os.PathLike[str] | Sequence[Pair],
        out: str | os.PathLike[str],
        concurrency: int = 4,
        **kwargs: Any,
    ) -> BatchSummary:
        """Register every pair of a CSV file (columns ``source``, ``target``; optional ``id``, ``T_target_source``)
        into the JSON-lines file ``out``, ``concurrency`` pairs at a time; resumable (ids already in ``out`` are
        skipped); retried with backoff on 502/503 and connection errors, never on other errors.

        ``kwargs``: ``retry`` (a ``RetryPolicy``; default: 5 retries), ``shard_index``/``shard_count``,
        ``retry_errors``, ``progress``, ``jitter_seed``, and the options of ``register`` (``icp``, ``init``,
        ``policy``, ...). See ``pranet.client.batch``.
        """
        from pranet.client.batch import register_many

        return register_many(self, pairs, out, concurrency, **kwargs)
