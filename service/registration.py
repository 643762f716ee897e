"""One registration request, framework-free: body bytes -> clouds and a ``RegistrationConfig`` -> the engine ->
response.

``request_config`` is the one place where a request's options become the registration's. Runs in a worker
thread (it is CPU-bound); raises ``RequestError`` for anything the client can fix.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from pydantic import ValidationError

from pranet.core.agent import AgentTimeout
from pranet.core.preprocess import DegenerateCloudError
from pranet.core.registration_config import SERVICE_DEFAULT, RegistrationConfig
from pranet.core.registration_types import Registration
from pranet.core.wire import WireError, point_count
from pranet.core.wire import decode_cloud as decode_wire
from pranet.engine.engine import Engine
from pranet.service.schemas import (
    MAX_ABS_COORDINATE,
    MIN_POINTS,
    EncodedCloud,
    ExitCheck,
    IcpInfo,
    ModelInfo,
    RegisterRequest,
    RegisterResponse,
    TrajectoryStep,
)


class RequestError(Exception):
    """A request the service refuses: ``status`` (HTTP) and ``detail`` (message or field errors)."""

    def __init__(self, status: int, detail: str | list[dict]):
        super().__init__(detail if isinstance(detail, str) else str(detail))
        self.status = status
        self.detail = detail


def validation_detail(error: ValidationError) -> list[dict]:
    """pydantic's errors without the (possibly huge) input echo or non-JSON context."""
    return error.errors(include_url=False, include_input=False, include_context=False)


@dataclass(frozen=True)
class CloudLimits:
    """The most points per cloud (``PRANET_MAX_POINTS``), and per cloud sent as a JSON list (``PRANET_MAX_LIST_POINTS``:
    a list costs about 3 us a point to parse, base64 about 0.06 us)."""

    max_points: int
    max_list_points: int

    @property
    def list_points(self) -> int:
        return min(self.max_points, self.max_list_points)


_SEND_BASE64 = "send it base64-encoded (pranet-client does above 5000 points), downsample it, or raise the limit"
_BRACKET_SLACK = 16  # '[' outside the clouds' points: the two clouds' own lists, steps, exit_checks


def parse_request(body: bytes, limits: CloudLimits) -> RegisterRequest:
    # Every point of a JSON list opens a '['; counting them (milliseconds for 40 MB) bounds the parse's cost
    # before it starts: parsing 40 MB of "[0,0,0]," would take about 13 s.
    if body.count(b"[") > 2 * limits.list_points + _BRACKET_SLACK:
        raise RequestError(
            413,
            f"request body holds more than {2 * limits.list_points:,} points as JSON lists, more than this server's "
            f"limit of {limits.list_points:,} per cloud for lists ({_list_limit_name(limits)}); "
            "send clouds base64-encoded (pranet-client does above 5000 points), downsample them, or raise the limit",
        )
    try:
        return RegisterRequest.model_validate_json(body)
    except ValidationError as e:
        raise RequestError(422, validation_detail(e)) from None


def _list_limit_name(limits: CloudLimits) -> str:
    return "PRANET_MAX_LIST_POINTS" if limits.max_list_points < limits.max_points else "PRANET_MAX_POINTS"


def _too_many(name: str, n: int, limit: int, setting: str, fix: str, form: str = "") -> RequestError:
    return RequestError(
        413, f"{name}: {n:,} points{form}, more than this server's limit of {limit:,} ({setting}); {fix}"
    )


def decode_cloud(cloud: list[list[float]] | EncodedCloud, name: str, limits: CloudLimits) -> np.ndarray:
    """A request cloud -> ``(N, 3)`` float64; 413 past the limits (with the count and the fix), 422 for
    undecodable data."""
    if isinstance(cloud, EncodedCloud):
        n = point_count(cloud.data)  # from the length alone: a cloud over the limit is never decoded
        if n > limits.max_points:
            raise _too_many(name, n, limits.max_points, "PRANET_MAX_POINTS", "downsample the cloud or raise the limit")
        try:
            points = decode_wire(cloud.data)
        except WireError as e:
            raise RequestError(422, f"{name}.data: {e}") from None
        if len(points) < MIN_POINTS:  # a list's length is checked by the schema's minItems
            raise RequestError(
                422, f"{name}: needs at least {MIN_POINTS} points (3 always lie in a plane), got {len(points)}"
            )
        # NaN/inf are reported by check_cloud (in register); finite but huge values are refused here.
        finite = points[np.isfinite(points)]
        if finite.size and np.abs(finite).max() > MAX_ABS_COORDINATE:
            raise RequestError(422, f"{name}: coordinates must satisfy |x| <= {MAX_ABS_COORDINATE:g}")
        return points
    if len(cloud) > limits.list_points:
        setting = _list_limit_name(limits)
        raise _too_many(name, len(cloud), limits.list_points, setting, _SEND_BASE64, form=" as a JSON list")
    return np.asarray(cloud, dtype=np.float64).reshape(-1, 3)  # (N, 3); the schema fixed 3 per point


def _matrix(a: np.ndarray) -> list[list[float]]:
    return [[float(x) for x in row] for row in a]


def _finite_or_none(x: float | None) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


def request_config(
    req: RegisterRequest, n_scales: int, base: RegistrationConfig = SERVICE_DEFAULT, fine_call: bool = True
) -> RegistrationConfig:
    """The registration a request asks for: ``base`` (the service's default) with the request's options.

    ``icp: false`` is the paper's PRANet-v1 (no ICP, so no exit checks or rescues); exit checks apply to the
    identity start only; ``rescue: false`` turns the rescues off, ``global_match: false`` the classical global
    candidate, ``walk: false`` the walk (a network call per step, as the paper), ``polish: false`` the polish,
    ``robust_icp: false`` the ICP's kernel on sparse clouds, ``agent_points: null`` the agent's points (the model's
    own then). ``fine_matching: true`` (with ``walk: false``; ``fine_call``: the model has ``score_fine.onnx``) the
    fine phase's own network call; ``null`` that call where the model has it and the walk is off (as ``PAPER_V1`` and
    ``PAPER_V2`` in process), ``false`` the trained call in both phases.
    """
    if req.steps is not None and len(req.steps) != n_scales:
        raise RequestError(422, f"steps: the model has {n_scales} step-size scales, so steps needs {n_scales} counts")
    if req.fine_matching and req.walk:
        raise RequestError(422, "fine_matching scores every fine step by the network: it needs walk=false")
    if req.fine_matching and not fine_call:
        raise RequestError(422, "fine_matching: the served model has no fine-phase call (score_fine.onnx)")
    refine = req.icp
    return base.with_(
        icp_stages=base.icp_stages if refine else (),
        icp_kernel=base.icp_kernel if refine and req.robust_icp else None,
        exit_checks=tuple(req.exit_checks) if refine and req.init == "identity" else (),
        rescue_window=base.rescue_window if refine and req.rescue else None,
        rescue_restarts=base.rescue_restarts and refine and req.rescue,
        rescue_shifts=base.rescue_shifts if refine and req.rescue else (),
        rescue_global_starts=base.rescue_global_starts if refine and req.rescue else None,
        rescue_turns=base.rescue_turns if refine and req.rescue else None,
        global_match=base.global_match and refine and req.global_match,
        init=req.init,
        n_starts=req.starts,
        agent_points=req.agent_points,
        policy=req.policy,
        early_stop=req.early_stop,
        schedule=tuple(req.steps) if req.steps is not None else None,
        walk_steps=base.walk_steps if req.walk else 0,
        fine_matching=req.fine_matching,
        polish=base.polish and refine and req.polish,
    )


def run_registration(
    body: bytes,
    engine: Engine,
    model_info: dict,
    limits: CloudLimits,
    deadline: float,
    admitted_at: float | None = None,
) -> RegisterResponse:
    """Parse ``body`` (JSON bytes), register with ``engine``, and build the response.

    ``deadline``: ``time.monotonic()`` seconds; ``admitted_at``: ``time.perf_counter()`` when the request
    was admitted (its wait for a free slot is reported as ``timing_ms["queue"]``).
    """
    t0 = time.perf_counter()
    queue_ms = (t0 - admitted_at) * 1e3 if admitted_at is not None else 0.0
    # 1. Parse the request, decode both clouds, and map the options.
    req = parse_request(body, limits)
    source = decode_cloud(req.source, "source", limits)
    target = decode_cloud(req.target, "target", limits)
    config = request_config(req, len(engine.scorer.schedule), fine_call=getattr(engine.scorer, "has_fine_call", False))
    decode_ms = (time.perf_counter() - t0) * 1e3
    if time.monotonic() > deadline:
        raise RequestError(504, "registration exceeded the server's time limit before it started (queued too long)")
    # 2. Register.
    try:
        result: Registration = engine.register(
            source, target, config, np.random.default_rng(req.seed), deadline, seed=req.seed
        )
    except DegenerateCloudError as e:
        raise RequestError(422, str(e)) from None
    except AgentTimeout as e:
        raise RequestError(504, f"{e} (server limit; ask for fewer steps or a smaller cloud)") from None
    # 3. Build the response, in the input units.
    return build_response(result, req, model_info, {"queue": queue_ms, "decode": decode_ms}, t0)


def build_response(
    result: Registration, req: RegisterRequest, model_info: dict, timing: dict[str, float], t0: float
) -> RegisterResponse:
    T = result.T_target_source
    confidence = result.confidence
    assert confidence is not None  # register computes it for every result
    timing = {**timing, **result.timing_ms}
    timing["total"] = (time.perf_counter() - t0) * 1e3
    return RegisterResponse(
        transform=_matrix(T),
        rotation=_matrix(T[:3, :3]),
        translation=[float(x) for x in T[:3, 3]],
        trajectory=[TrajectoryStep(step=s, action=name, transform=_matrix(Ts)) for s, name, Ts in result.trajectory]
        if req.return_trajectory
        else [],
        icp=IcpInfo(
            applied=result.icp is not None,
            fitness=_finite_or_none(result.icp.fitness) if result.icp else None,
            inlier_rmse=_finite_or_none(result.icp.inlier_rmse) if result.icp else None,
        ),
        timing_ms=timing,
        model=ModelInfo(**model_info),
        n_source=result.n_source,
        n_target=result.n_target,
        confidence=confidence.score,
        status=confidence.status,
        matches=confidence.matches,
        initial_transform=_matrix(result.initial_transform),
        exit_checks=[ExitCheck(step=step, confidence=score) for step, score in result.checks],
        rescued=result.rescued,
        candidate=result.candidate,
        candidates=result.candidates,
        network_calls=result.network_calls,
        spacing=result.resolution.spacing if result.resolution else None,
    )
