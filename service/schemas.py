"""Request and response bodies of the HTTP API (pydantic v2). No logic here: see ``registration.py``.

Frame convention: every transform is ``T_target_source``, a 4x4 homogeneous matrix that maps the
source onto the target: ``target ≈ R @ source + t``, in the units of the input clouds.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Discriminator, Field, Tag

from pranet.core.confidence import CERTIFYING_MATCHES
from pranet.core.registration_config import MAX_AGENT_POINTS, MIN_AGENT_POINTS, PAPER_AGENT_POINTS, SERVICE_DEFAULT
from pranet.core.registration_types import CandidateName, RescueName
from pranet.core.starts import DEFAULT_STARTS, MAX_STARTS
from pranet.core.wire import BYTES_PER_POINT, ENCODING, encoded_length

MAX_ABS_COORDINATE = 1e9  # input units; keeps every intermediate (centroids, SVD) far from overflow
MAX_STEPS_PER_SCALE = 200
MIN_POINTS = 4  # three points always lie in one plane, and a registration needs 3-D extent
# The base64 of N points (12 N bytes, a multiple of 3) is exactly 16 N characters, never padded.
ENCODED_POINT = f"[A-Za-z0-9+/]{{{encoded_length(1)}}}"


def _integral(value: Any) -> Any:
    """JSON Schema's "integer" includes 1.0: take an integral float as the int it is (1.5 stays an error)."""
    return int(value) if isinstance(value, float) and value.is_integer() else value


def json_int(**bounds: int) -> Any:
    """An int field that takes an integral float too ("1" and true stay errors); ``bounds``: ge, le."""
    return Annotated[int, Field(**bounds), BeforeValidator(_integral)]  # the bounds inside: the schema shows them


Coordinate = Annotated[
    float,
    Field(
        strict=True,
        allow_inf_nan=False,
        ge=-MAX_ABS_COORDINATE,
        le=MAX_ABS_COORDINATE,
        description="a coordinate in the cloud's own units (any: m, mm, ...)",
    ),
]
Point = Annotated[list[Coordinate], Field(min_length=3, max_length=3, description="[x, y, z]")]
Matrix4 = Annotated[list[list[float]], Field(min_length=4, max_length=4, description="4x4 row-major matrix")]


class _Strict(BaseModel):
    """Request bodies: unknown fields are errors, and no coercion ("1" is no int, 0 is no bool)."""

    model_config = ConfigDict(extra="forbid", strict=True)


class EncodedCloud(_Strict):
    """A cloud as ``N * 3`` little-endian float32 values ``x0 y0 z0 x1 y1 z1 ...``, base64-encoded (RFC 4648).

    About 4x smaller and 40x faster to parse than the nested list; ``N`` is ``len(data) / 16``. Clouds of more
    than 200,000 points (PRANET_MAX_LIST_POINTS) must use it.
    """

    encoding: Literal["base64-float32-le"] = Field(description="the only encoding: base64 of float32 little-endian")
    # The grammar is in the schema; decode_cloud checks it (with messages that say what is wrong).
    data: str = Field(
        description=f"standard base64 of N*3 float32 little-endian values, row-major (N, 3): {encoded_length(1)} "
        f"characters per point ({BYTES_PER_POINT} bytes), never padded; N >= {MIN_POINTS}, finite, |x| <= "
        f"{MAX_ABS_COORDINATE:g}; the most points: maxLength / {encoded_length(1)} (PRANET_MAX_POINTS)",
        examples=["AAAAAAAAAAAAAAAAAACAPwAAAAAAAAAAAAAAAAAAgD8AAAAAAAAAAAAAAAAAAIA/AACAPwAAgD8AAIA/"],
        # "format" names what the pattern cannot say (finite float32 values within the bounds), for client and
        # test generators that know the encoding.
        json_schema_extra={"format": ENCODING, "pattern": f"^(?:{ENCODED_POINT}){{{MIN_POINTS},}}$"},
    )


def _cloud_kind(value: Any) -> str:
    return "encoded" if isinstance(value, dict | EncodedCloud) else "list"


PointList = Annotated[
    list[Point],
    Field(
        min_length=MIN_POINTS,
        description=f"nested list of N >= {MIN_POINTS} points [[x, y, z], ...]; the most points: maxItems "
        "(PRANET_MAX_LIST_POINTS; larger clouds must be base64-encoded)",
    ),
]
Cloud = Annotated[
    Annotated[PointList, Tag("list")] | Annotated[EncodedCloud, Tag("encoded")],
    Discriminator(_cloud_kind),
    Field(
        description=(
            "a point cloud (N, 3) in any units: EITHER a nested list [[x, y, z], ...] OR "
            f'{{"encoding": "{ENCODING}", "data": "<base64>"}}. Coordinates must be finite with '
            f"|x| <= {MAX_ABS_COORDINATE:g}, and the points must span 3-D (not all on one plane or line): else 422. "
            "More points than the server's limits (PRANET_MAX_POINTS, PRANET_MAX_LIST_POINTS for a list): 413."
        )
    ),
]


class RegisterRequest(_Strict):
    """Register ``source`` onto ``target``; the answer is ``T_target_source`` (target ≈ R @ source + t)."""

    # The one rule between fields, stated in the schema so a client (or a fuzzer) generated from it can keep it:
    # ``fine_matching: true`` needs ``walk: false``. ``request_config`` enforces it with a 422.
    model_config = ConfigDict(
        json_schema_extra={
            "if": {"properties": {"fine_matching": {"const": True}}, "required": ["fine_matching"]},
            "then": {"properties": {"walk": {"const": False}}, "required": ["walk"]},
        }
    )

    source: Cloud
    target: Cloud
    icp: bool = Field(
        True, description="refine the agent's estimate with ICP (PRANet-v2): point-to-plane, then point-to-point"
    )
    robust_icp: bool = Field(
        True,
        description="with icp, on sparse clouds (a few hundred or thousand points over the object): weigh the "
        "point-to-plane matches by Tukey's biweight, so that points beyond the overlap do not pull the result; "
        "false: least squares (the paper's PRANet-v2)",
    )
    policy: Literal["deterministic", "stoch1", "stoch2"] = Field(
        "deterministic", description="action choice: argmax, or one of the paper's stochastic policies"
    )
    early_stop: bool = Field(False, description="end a step-size scale once no action has a positive predicted reward")
    seed: json_int(ge=0, le=2**32 - 1) = Field(0, description="seed of the resampling and stochastic policies")
    steps: list[json_int(ge=0, le=MAX_STEPS_PER_SCALE)] | None = Field(
        None,
        min_length=1,
        max_length=8,
        description=(
            "agent steps per step-size scale, one count per scale of the model (the shipped model: "
            "[coarse, fine], default [20, 40]); null = the model's schedule"
        ),
        examples=[[20, 40]],
    )
    exit_checks: list[json_int(ge=1, le=8 * MAX_STEPS_PER_SCALE)] = Field(
        list(SERVICE_DEFAULT.exit_checks),
        max_length=16,
        description="with icp: after these many agent steps (cumulative), refine with ICP and return at once if the "
        "result is 'converged' (most pairs need only 10 coarse steps); with the global match, it runs after the "
        "last check of the coarse phase unless a check was sure; [] = always run every step (the paper's PRANet-v2)",
        examples=[[10, 20, 40], []],
    )
    rescue: bool = Field(
        True,
        description="with icp: when the result is still 'suspect', try the coarse phase again from six starts 30° "
        "around the best estimate, on sparse clouds ICP from the best estimate shifted along each axis, a "
        "wide-window ICP from the input pose, and last, on sparse clouds whose best result is still far from "
        "'converged', the agent from the global mode's `starts` rotations (not again with init='global'); the most "
        "confident result is kept",
    )
    global_match: bool = Field(
        True,
        description="with icp: when the agent's result is not 'converged' after its coarse phase, try the classical "
        "global match (features at the data's resolution and a robust solver, from any initial pose), refined the "
        "same way; the most confident candidate wins (with init='global' too, unless a start is already sure)",
    )
    walk: bool = Field(
        True,
        description="let the agent take several steps toward one estimated pose between network calls (a few calls "
        "per registration); false: the paper's protocol, a network call per step",
    )
    fine_matching: bool | None = Field(
        None,
        description="with walk=false: the fine phase's network calls match the clouds where the agent has put "
        "them, on the model's position-led matching rounds only (score_fine.onnx); on partial overlap the agent "
        "alone then stays nearer the truth. null (default): so where the model has that call and walk is false, "
        "as the paper's configurations run in process; false: the trained call in both phases",
    )
    polish: bool = Field(
        True,
        description="with icp: refine the winning result once more: with generalized ICP where the surface is "
        "smooth at its resolution (dense range scans), with symmetric robust point-to-point ICP on sparse samples "
        "that overlap in part",
    )
    return_trajectory: bool = Field(True, description="include the agent's transform after every step")
    init: Literal["identity", "global"] = Field(
        "identity",
        description="where the agent starts: 'identity' (the input pose; the model knows rotations up to 60°) or "
        "'global' (from `starts` well-spread rotations at once, for any initial rotation; the most confident "
        "results are refined by ICP and the best is returned; about `starts` times the agent's coarse work; with an "
        "exit check in the coarse phase, a sure best start at its end returns at once)",
    )
    agent_points: json_int(ge=MIN_AGENT_POINTS, le=MAX_AGENT_POINTS) | None = Field(
        SERVICE_DEFAULT.agent_points,
        description="points per cloud the agent's network sees (a random subset, each point once, all of a smaller "
        f"cloud; ICP and the confidence use every point); null: the model's own; the paper's configurations use "
        f"{PAPER_AGENT_POINTS}",
    )
    starts: json_int(ge=1, le=MAX_STARTS) = Field(
        DEFAULT_STARTS,
        description="init='global' only: number of start rotations (24 = the rotations of the cube, every rotation "
        "within 63° of one)",
    )


class TrajectoryStep(BaseModel):
    step: int = Field(description="0-based agent step")
    action: str = Field(description="action name, e.g. 'rot+x:10deg' or 'trans-z:0.1' (unit-frame step)")
    transform: Matrix4 = Field(description="T_target_source after this step, input units")


class IcpInfo(BaseModel):
    applied: bool = Field(description="whether ICP refined the agent's estimate")
    fitness: float | None = Field(description="fraction of source points with a target match within the ICP radius")
    inlier_rmse: float | None = Field(description="RMS distance of the inlier matches, input units")


class ExitCheck(BaseModel):
    step: int = Field(description="agent steps taken before this check")
    confidence: float = Field(description="confidence of the ICP-refined estimate at this check")


class ModelInfo(BaseModel):
    name: str | None
    version: str | None
    sha256: str = Field(description="sha256 over both ONNX graphs' digests")


class RegisterResponse(BaseModel):
    transform: Matrix4 = Field(description="T_target_source (4x4): target ≈ R @ source + t, input units")
    rotation: list[list[float]] = Field(min_length=3, max_length=3, description="R (3x3), the rotation of transform")
    translation: list[float] = Field(min_length=3, max_length=3, description="t (3,), input units")
    trajectory: list[TrajectoryStep] = Field(description="the agent's steps; empty if return_trajectory is false")
    icp: IcpInfo
    timing_ms: dict[str, float] = Field(
        description="milliseconds per stage: queue (waiting for a slot), decode, preprocess, target_embedding, "
        "agent_steps, icp, confidence, rescue; total (decode to response, queue excluded)"
    )
    model: ModelInfo
    n_source: int = Field(description="points received in source")
    n_target: int = Field(description="points received in target")
    confidence: float = Field(
        ge=0.0,
        le=1.0,
        description="how tight the region where the clouds overlap is, at the data's own resolution: of the points "
        "that the result brings within one voxel (4 spacings) of the other cloud, the fraction within one spacing, the "
        "smaller of the two directions (scaled down when under 10 % of either cloud overlaps); it does not fall with "
        "partial overlap",
    )
    status: Literal["converged", "suspect"] = Field(
        description="'converged' when confidence reaches the calibrated threshold, or when the result is a global "
        f"match resting on at least {CERTIFYING_MATCHES} mutually consistent feature matches (see matches) that its "
        "ICP refinement kept; else 'suspect' (check the result)"
    )
    matches: int = Field(
        0,
        ge=0,
        description="the feature matches that certify a global match's result as 'converged' whatever its "
        "confidence (dense scans where the overlap's tightness cannot judge, such as ring LiDAR); 0: the status "
        "follows the confidence",
    )
    initial_transform: Matrix4 = Field(
        description="the agent's start pose, T_target_source in input units: the identity, or with init='global' "
        "the winning start (the trajectory begins there)"
    )
    exit_checks: list[ExitCheck] = Field(
        default_factory=list,
        description="the exit checks that ran, in order; the agent stopped after a converged one (before the global "
        f"match, only at confidence {SERVICE_DEFAULT.exit_confidence} or more). On dense scans a check whose estimate "
        "is still doubtful after the first ICP iterations waits behind the global match and is listed only if it "
        "was refined after all",
    )
    rescued: RescueName | None = Field(
        None,
        description="which rescue won over the agent's result (null: none ran or none was more confident); with "
        "'restarts' or 'global_starts' the trajectory and initial_transform are the winning start's",
    )
    candidate: CandidateName = Field(
        "agent",
        description="which candidate won: 'agent' (the agent's estimate, refined by ICP), 'global_match' (the "
        "classical global match, for any initial pose, refined by ICP), 'restarts', 'wide_icp', 'shifted_icp', "
        "'global_starts' or 'turned_icp' (the rescues; 'shifted_icp': ICP from the best estimate moved along an "
        "axis, on sparse clouds; 'global_starts': the agent from the global mode's starts, on sparse clouds; "
        "'turned_icp': ICP from the best estimate turned by well-spread rotations, about where it puts the source "
        "and with the source centroid on the target's, the last rescue on sparse clouds)",
    )
    candidates: dict[str, float] = Field(
        default_factory=dict, description="every candidate tried this request -> its best confidence"
    )
    network_calls: int = Field(
        0,
        description="how many source poses the reward network scored this request: full network evaluations, and the "
        "fine phase's match-only calls (its matching rounds on a translated source); not the translations "
        "re-scored by the reward layer alone",
    )
    spacing: float | None = Field(
        None,
        description="the data's resolution, input units: the median nearest-neighbour distance of the coarser cloud; "
        "every distance of the registration (voxel, ICP windows, inlier distance) is a multiple of it",
    )


class HealthResponse(BaseModel):
    status: Literal["ok"] = "ok"


class ReadyResponse(BaseModel):
    status: Literal["ready"] = "ready"
    model: ModelInfo
    in_flight: int = Field(description="registrations admitted and not yet answered (this worker)")
    max_concurrency: int
    max_queue: int


class ErrorResponse(BaseModel):
    detail: str | list[dict[str, Any]] = Field(description="what went wrong: a message, or a list of field errors")


def document_limits(
    components: dict[str, Any], max_points: int, max_list_points: int, n_scales: int | None = None
) -> None:
    """Write a server's own limits into the OpenAPI ``components`` built from these models, so that the schema
    says what this server accepts: the most points per cloud as a list (``maxItems``) and base64-encoded
    (``maxLength``), and the steps' length (one count per scale of the served model, when it is loaded)."""
    request = components["RegisterRequest"]["properties"]
    for name in ("source", "target"):
        for variant in request[name]["oneOf"]:
            if variant.get("type") == "array":
                variant["maxItems"] = min(max_points, max_list_points)
    components["EncodedCloud"]["properties"]["data"]["maxLength"] = encoded_length(max_points)
    if n_scales is not None:
        for variant in request["steps"]["anyOf"]:
            if variant.get("type") == "array":
                variant["minItems"] = variant["maxItems"] = n_scales
