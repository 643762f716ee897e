"""What a registration does, as data: one frozen ``RegistrationConfig``, and the named configurations.

The one source of truth for the registration knobs: ICP stages and windows, exit checks, rescues, the
confidence threshold, global-mode starts, the policy and the schedule. ``core.pipeline.register`` reads it;
``pranet.engine`` builds the ICP functions it names; the service maps a request onto ``SERVICE_DEFAULT``;
``pranet-eval`` and ``pranet-bench`` run ``PAPER_V1``, ``PAPER_V2`` and ``SERVICE_DEFAULT``.
Data only (no ICP, no model), so that every layer may import it. Why each default is what it is: docs/DESIGN.md.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from pranet.core.confidence import DEFAULT_THRESHOLD
from pranet.core.starts import DEFAULT_STARTS, MAX_STARTS

POINT_TO_POINT, POINT_TO_PLANE = "point_to_point", "point_to_plane"
ICP_METHODS = (POINT_TO_POINT, POINT_TO_PLANE)
IcpStage = tuple[str, float]  # (estimation method, max correspondence distance in spacings of the data)
INITS = ("identity", "global")
POLICIES = ("deterministic", "stoch1", "stoch2")

# ICP windows are multiples of the data's spacing (``core.resolution``): the median nearest-neighbour distance,
# so they mean the same on a 0.5 mm bunny scan, a 6 mm RGB-D fragment and a ModelNet40 shape (where 4 and 2
# spacings are about the 0.1 and 0.05 unit-frame windows PRANet-v2 used before: docs/DESIGN.md, "ICP of
# PRANet-v2" and "Resolution first"). A first pass at 2 voxels (8 spacings) widens the basin for the agent's and
# the global match's estimates, which are degrees off on real scans.
ICP_WIDE_WINDOW = 8.0
ICP_WINDOW = 4.0
ICP_REFINE_WINDOW = 2.0
# The rescue's wide ICP from the input pose: a window of half the unit sphere (the ICP baseline's), a fraction of
# the clouds' extent rather than of their spacing.
RESCUE_WINDOW = 0.5
# The service's agent walks up to this many steps toward one estimated pose before asking the network again
# (``core.agent``): validation pairs, docs/DESIGN.md, "The walk".
WALK_STEPS = 10
# A candidate whose quick confidence after the first (8-spacing) ICP stage is under a quarter of the status threshold
# is not refined further: on the real scans wrong agent estimates scored 0.00-0.16 there and right ones (the
# agent's and the global match's) 0.28-0.91, and the finer stages of a wrong one cost 40-60 ms; at half the
# threshold ModelNet40 partial pairs lost right candidates (47.5 -> 32.5 % of 40): docs/DESIGN.md, "The ICP gate".
ICP_GATE = 0.25
# An agent estimate ends the request before the global match only this sure: between the status threshold and this,
# the global match's cheapest candidate is tried beside it and the more confident wins. On RGB-D fragments cut to
# 40-60 % the agent slid along walls to answers 7-18° off that scored 0.43-0.46 (`converged`), where right ones
# scored 0.46-0.57; every early exit on ModelNet40 (noisy, partial) and on the object scans scored 0.64 or more
# (docs/DESIGN.md, "A surer bar for ending before the global match").
EXIT_CONFIDENCE = 0.55
# The service's point-to-plane stages weigh each match on sparse clouds (not ``Resolution.dense``: ModelNet40's
# samples) by Tukey's biweight of its distance, with this many spacings as its scale. There a window of 8 spacings
# spans a good part of the object, and on a partial pair the points beyond the overlap, matched to the nearest rim,
# dragged the result off: from the true pose, the stages ended right on 58 of 100 partial pairs by least squares and
# on 85 with the kernel; the service default went from 82 to 103 of 150 partial pairs with the same successes on
# clean and noisy ones. It narrows the basin of a far-off estimate on whole shapes (from 55° off: 24 of 40 against
# 39), so the paper's v2, whose agent can end that far off, keeps least squares; dense scans do too (there it only
# slowed the exit checks and moved the LiDAR pair 0.19 -> 0.36°): docs/DESIGN.md, "A robust kernel on sparse clouds".
ICP_KERNEL = 2.0
# On sparse clouds a still unconfident result is also refined from the best estimate moved by these distances
# (unit frame: fractions of the clouds' radius) along each axis: on a partial pair the agent can turn the source
# right and leave it 0.15-0.5 off along the target (ModelNet40 partial, 150 pairs: 103 -> 109 right with 0.15 and
# 0.3, with the finish 118 -> 120 adding 0.45 and 123 adding 0.6, no more with 0.8; noisy and clean unchanged;
# docs/DESIGN.md, "A finish for partial overlap"). At most 24 ICP runs of a few milliseconds there, until one is
# confident; dense clouds, where each costs 50-300 ms, have the global match instead.
RESCUE_SHIFTS = (0.15, 0.3, 0.45, 0.6)
# Last, on sparse clouds, the agent from the global mode's starts, where the best confidence is still under this
# fraction of the status threshold: on the 1266 partial test pairs, run on every unconfident result, it made right six
# answers that had scored 0.35-0.44 (at most 0.71 of the sparse threshold, 0.62) and one that had scored 0.54, and
# turned one right answer (0.52) wrong; the right answers that end `suspect` score 0.45 and up. Under the gate it
# runs on a fifth of those requests (docs/DESIGN.md, "The global mode's starts as the last rescue").
GLOBAL_STARTS_BELOW = 0.72
# Last of all, on sparse clouds, ICP from the best estimate turned about where it puts the source by each of
# ``TURNS`` well-spread rotations but the identity (``TURNS - 1`` starts, until one is confident), where the best
# confidence is still under this fraction of the status threshold. On a partial pair of a nearly symmetric shape the
# agent and the other rescues end on a turned copy of the truth (a half or a quarter turn, or 40-80° off) that no
# 30° restart leaves, while the truth scores higher than that answer (168 of the 178 failures more than 5° off, of
# the 1266 partial test pairs); the local refiners reach the truth from few starts near it, so many starts are needed.
# On those 1266 pairs 60 turns made 46 wrong answers right and 5 right ones wrong, four of them half-turns that score
# higher (75.7 -> 78.9 %); 120 made 58 right and lost 4 (79.9 %), at 1.3× the 60 turns' mean time. The answers they
# made right had scored under 0.9 of the threshold (docs/DESIGN.md, "ICP from turned copies of the answer").
TURNED_ICP_BELOW = 0.9
TURNS = 120
# Then the ``CENTRED_TURNS - 1`` turns of that many well-spread rotations with the moved source's centroid put on the
# target's: a partial answer's translation can be as far off as its rotation. On the 1266 partial pairs after the 120
# turns: 15 more right, none lost (79.9 -> 81.1 %), at 1.3× the rescue's mean time (docs/DESIGN.md, "ICP from turned
# copies of the answer").
CENTRED_TURNS = 60
# The service's agent sees this many points per cloud, not the 256 the network was trained on (nothing in the network
# fixes N; its graph and matching cost grow with N²): a network call takes half the time, and ICP, which works on
# every point, finishes what the coarser estimate leaves. pranet-bench's first 100 unseen-category pairs per setting,
# side by side: the same success on clean and noisy pairs (100 / 100), 77 against 78 on partial ones, at 0.76-0.80×
# the median time (docs/DESIGN.md, "Fewer points for the service's agent"). The paper's configurations use
# PAPER_AGENT_POINTS.
SERVICE_AGENT_POINTS = 128
# The paper's configurations give the agent every point of the paper's 1024-point clouds: the paper samples 1024 points
# per cloud, and nothing in the network fixes N. On 150 validation pairs per setting, the agent alone was better on
# clean and noisy pairs with every point than with the 256 the model was trained on, at about 10× the time per pair
# (docs/DESIGN.md, "Every point for the paper's agent").
PAPER_AGENT_POINTS = 1024
# A request may ask for any count up to the paper's: more cost N² per call (with 120 global starts, far beyond the
# service's deadline) and bought the service nothing ("More points at inference").
MIN_AGENT_POINTS, MAX_AGENT_POINTS = 32, PAPER_AGENT_POINTS


def check_icp_stages(stages: tuple[IcpStage, ...]) -> None:
    """Raise ``ValueError`` unless every stage is a known method with a positive window."""
    for method, window in stages:
        if method not in ICP_METHODS or not window > 0:
            raise ValueError(f"bad ICP stage ({method!r}, {window}): method in {ICP_METHODS}, window > 0")


def two_windows(
    method: str, window: float = ICP_WINDOW, refine_window: float = ICP_REFINE_WINDOW
) -> tuple[IcpStage, ...]:
    """``method`` within ``window``, then again within ``refine_window`` from that result."""
    return ((method, window), (method, refine_window))


# Point-to-plane reaches the truth from farther off (8, 4, 2 spacings); a point-to-point finish (2, then 1 spacing)
# is more precise on noisy normals and cuts the pull of points beyond the overlap on partial pairs
# (docs/DESIGN.md, "ICP at the data's resolution").
DEFAULT_ICP_STAGES: tuple[IcpStage, ...] = (
    ((POINT_TO_PLANE, ICP_WIDE_WINDOW),) + two_windows(POINT_TO_PLANE) + two_windows(POINT_TO_POINT, 2.0, 1.0)
)


@dataclass(frozen=True)
class RegistrationConfig:
    """Everything about a registration but the clouds, the model and the seed.

    ``icp_stages``: the refinement, one Open3D ICP pass per ``(method, window in spacings)`` from the previous
    result; ``()`` = no ICP (PRANet-v1). ``global_match``: with ICP, a classical global candidate (features and a
    robust solver) when the agent is not ``sure``, in both modes. With ICP:
    ``exit_checks`` refine after those cumulative agent steps and stop once the
    result is confident (identity mode; with ``global_match``, it runs after the last check of the coarse phase
    unless a check before was ``sure``); ``rescue_window`` (or ``None``) runs a wide ICP from the input pose when
    the result stays below ``threshold``, ``rescue_restarts`` reruns the coarse phase from six starts 30°
    around the best estimate, ``rescue_shifts`` refines the best estimate moved by each distance along each
    axis (sparse clouds), and last, where the best confidence is still under ``rescue_global_starts`` times the
    status threshold (``None``: never), the agent's coarse phase from the ``n_starts`` rotations of the global mode,
    its ``refine_top`` most confident refined (sparse clouds), then, under ``rescue_turns`` times the threshold
    (``None``: never), ICP from the best estimate turned by each of ``TURNS - 1`` well-spread rotations, then by
    ``CENTRED_TURNS - 1`` with the source centroid put on the target's (sparse clouds). ``init="global"``
    starts the agent from ``n_starts`` rotations and refines the ``refine_top`` most confident; with an exit check in
    the coarse phase, the most confident start is refined first at its end and a ``sure`` one ends the request; an
    unconfident result gets the rescues (all but the global starts, which the mode has run). ``schedule``: steps
    per step-size scale (``None`` = the model's).
    ``walk_steps``: 0 = the paper's protocol, a network call per step; ``k > 0`` = walk up to ``k`` steps toward
    one estimated pose in closed form before asking the network again (``core.agent``; models with the analytic
    reward layer only, others call it every step). ``confirm_arrival``: when the walk arrives, ask the network
    again before ending the scale (``False`` is honoured only with ICP after the agent: the agent alone always
    confirms). ``polish``: with ICP, refine the winning candidate once more (small_gicp's GICP where the surface
    is smooth at its resolution; ``engine.polish``). ``icp_gate``: a candidate whose quick confidence after the
    first ICP iterations is below ``icp_gate`` times the status threshold is not refined further (``None``: every
    candidate gets every stage). ``exit_confidence``: with ``global_match``, the confidence an exit check before it
    needs to end the request (``None``: the status threshold); a ``converged`` result below it gets the global
    match as a rival. ``icp_guard``: keep a candidate's estimate instead of its ICP result when that
    scores lower (off for the paper's v2: its ICP result, whatever it is). ``defer_doubtful``: with ``icp_gate``
    and ``global_match``, on dense clouds, an agent estimate (or a global candidate) that does not yet look
    ``converged`` after the gate's iterations waits, part-refined; the waiting ones are refined best first once the
    next global candidate has been seen, until one is ``sure``. ``icp_kernel``: on sparse clouds, the
    point-to-plane stages weigh each match by Tukey's biweight with this scale in spacings (``None``: least squares,
    the paper's v2). ``agent_points``: points per cloud the agent sees, each point once (all of a
    smaller cloud; ``None``: the model's own ``n_points``). ``fine_matching``: the fine phase's network calls match
    the clouds where the agent has put them, on the position-led rounds only (the model's ``score_fine.onnx``;
    a network call per step, so not with the walk); ``None``: when the model has that call and the agent makes a
    network call per step (``uses_fine_call``), ``False``: the trained call in both phases.
    """

    icp_stages: tuple[IcpStage, ...] = ()
    exit_checks: tuple[int, ...] = ()
    rescue_window: float | None = None
    rescue_restarts: bool = False
    global_match: bool = False
    threshold: float = DEFAULT_THRESHOLD
    init: str = "identity"
    n_starts: int = DEFAULT_STARTS
    refine_top: int = 3
    policy: str = "deterministic"
    early_stop: bool = False
    schedule: tuple[int, ...] | None = None
    walk_steps: int = 0
    confirm_arrival: bool = True
    polish: bool = False
    icp_gate: float | None = None
    exit_confidence: float | None = None
    icp_guard: bool = False
    defer_doubtful: bool = False
    icp_kernel: float | None = None
    rescue_shifts: tuple[float, ...] = ()
    agent_points: int | None = None
    rescue_global_starts: float | None = None
    rescue_turns: float | None = None
    fine_matching: bool | None = None

    def __post_init__(self) -> None:
        check_icp_stages(self.icp_stages)
        if self.rescue_window is not None and not self.rescue_window > 0:
            raise ValueError(f"rescue_window must be > 0 or None, got {self.rescue_window}")
        if self.rescue_global_starts is not None and not 0.0 < self.rescue_global_starts <= 1.0:
            raise ValueError(f"rescue_global_starts must be in (0, 1] or None, got {self.rescue_global_starts}")
        if self.rescue_turns is not None and not 0.0 < self.rescue_turns <= 1.0:
            raise ValueError(f"rescue_turns must be in (0, 1] or None, got {self.rescue_turns}")
        if self.init not in INITS:
            raise ValueError(f"unknown init {self.init!r}; choose from {INITS}")
        if self.policy not in POLICIES:
            raise ValueError(f"unknown policy {self.policy!r}; choose from {POLICIES}")
        if not 1 <= self.n_starts <= MAX_STARTS:
            raise ValueError(f"n_starts must be in [1, {MAX_STARTS}], got {self.n_starts}")
        if self.refine_top < 1:
            raise ValueError(f"refine_top must be >= 1, got {self.refine_top}")
        if self.icp_gate is not None and not 0.0 <= self.icp_gate <= 1.0:
            raise ValueError(f"icp_gate must be in [0, 1] or None, got {self.icp_gate}")
        if self.exit_confidence is not None and not 0.0 <= self.exit_confidence <= 1.0:
            raise ValueError(f"exit_confidence must be in [0, 1] or None, got {self.exit_confidence}")
        if self.agent_points is not None and not MIN_AGENT_POINTS <= self.agent_points <= MAX_AGENT_POINTS:
            raise ValueError(
                f"agent_points must be in [{MIN_AGENT_POINTS}, {MAX_AGENT_POINTS}] or None, got {self.agent_points}"
            )
        if self.icp_kernel is not None and not self.icp_kernel > 0:
            raise ValueError(f"icp_kernel must be > 0 or None, got {self.icp_kernel}")
        if self.walk_steps < 0:
            raise ValueError(f"walk_steps must be >= 0, got {self.walk_steps}")
        if self.fine_matching and self.walk_steps:
            raise ValueError("fine_matching scores every fine step by the network: it needs walk_steps=0")

    def uses_fine_call(self, available: bool) -> bool:
        """Whether the fine phase goes through the model's fine-phase call, for a model that has one (``available``)
        or not: ``True`` on a model without it is an error for the caller to raise."""
        if self.fine_matching is None:
            return available and not self.walk_steps
        return self.fine_matching

    @property
    def refines(self) -> bool:
        """Whether ICP refines the agent's result (PRANet-v2 and the service) or not (PRANet-v1)."""
        return bool(self.icp_stages)

    def with_(self, **changes: object) -> RegistrationConfig:
        """A copy with ``changes`` (validated again)."""
        return replace(self, **changes)  # type: ignore[arg-type]


# The paper's agent alone: 60 greedy steps, a network call each, no ICP, on the paper's 1024 points per cloud. The
# fine steps go through the model's fine-phase call when it has one (``fine_matching=None``), which keeps a
# near-aligned pair where it is better than the trained call (docs/DESIGN.md, "A fine-phase call");
# ``with_(fine_matching=False)`` is the trained call in both phases.
PAPER_V1 = RegistrationConfig(agent_points=PAPER_AGENT_POINTS)
# The paper's PRANet-v2: the agent's 60 steps, then ICP.
PAPER_V2 = PAPER_V1.with_(icp_stages=DEFAULT_ICP_STAGES)
# The service's default request: v2 with exit checks halfway through the coarse phase, at its end and halfway
# through the fine one, the global match when the agent is not sure, and the rescues of a still unconfident result.
SERVICE_DEFAULT = PAPER_V2.with_(
    # The walk reaches the first estimate's pose in a few steps, from which ICP mostly converges: a check after 10
    # steps saves the second network call (ModelNet40, 150 pairs each: median -13 % clean, -18 % noisy, the same
    # successes; docs/DESIGN.md, "An exit check halfway through the coarse phase").
    exit_checks=(10, 20, 40),
    global_match=True,
    rescue_window=RESCUE_WINDOW,
    rescue_restarts=True,
    walk_steps=WALK_STEPS,
    # ICP follows the agent, so an arrival ends the scale without a confirming network call: the same validation
    # success, a third fewer calls (docs/DESIGN.md, "The walk").
    confirm_arrival=False,
    polish=True,
    icp_gate=ICP_GATE,
    exit_confidence=EXIT_CONFIDENCE,
    icp_guard=True,
    defer_doubtful=True,
    icp_kernel=ICP_KERNEL,
    rescue_shifts=RESCUE_SHIFTS,
    agent_points=SERVICE_AGENT_POINTS,
    rescue_global_starts=GLOBAL_STARTS_BELOW,
    rescue_turns=TURNED_ICP_BELOW,
)
