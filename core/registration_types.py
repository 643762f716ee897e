"""The types a registration passes between its stages and to its callers: the refinement and global-match
functions the engine injects, a candidate result, and the final ``Registration``.

Every transform is ``T_target_source``: target ≈ R @ source + t. Inside the pipeline the clouds live in the
model's unit frame (``core.preprocess.Normalization``); a ``Registration`` is in the input's (world) units.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Literal, Protocol, get_args

import numpy as np

from pranet.core.agent import AgentResult
from pranet.core.confidence import Confidence
from pranet.core.preprocess import Normalization
from pranet.core.resolution import Resolution
from pranet.core.se3 import Array

# Which estimate won (the response's ``candidate``).
AGENT = "agent"  # the agent from the input pose (or, with init="global", from the best of its starts)
GLOBAL_MATCH = "global_match"  # the classical global match (features + robust solver), refined
RESTARTS = "restarts"  # the agent's coarse phase again from starts around the best estimate
WIDE_ICP = "wide_icp"  # ICP with a wide window from the input pose
SHIFTED_ICP = "shifted_icp"  # ICP from the best estimate moved along the axes (sparse clouds)
GLOBAL_STARTS = "global_starts"  # the agent's coarse phase from the global mode's starts (sparse)
TURNED_ICP = "turned_icp"  # ICP from the best estimate turned about itself by well-spread rotations, the last (sparse)
# the wire's names (the response's): the rescues, and every candidate
RescueName = Literal["restarts", "wide_icp", "shifted_icp", "global_starts", "turned_icp"]
RESCUES: tuple[str, ...] = get_args(RescueName)
CandidateName = Literal["agent", "global_match", RescueName]
CANDIDATES: tuple[str, ...] = get_args(CandidateName)


@dataclass(frozen=True)
class IcpResult:
    transform: Array  # (4, 4) T_target_source, unit frame
    fitness: float
    inlier_rmse: float  # unit frame


class IcpFn(Protocol):
    """``icp(source_unit (N, 3), target_unit (M, 3), init T_target_source (4, 4), resolution (unit frame))``.

    ``proceed``: asked with the estimate after the first stage; ``False`` ends the refinement there (a hopeless
    candidate is not worth the finer stages)."""

    def __call__(
        self,
        source: Array,
        target: Array,
        init: Array,
        resolution: Resolution,
        proceed: Callable[[Array], bool] | None = None,
    ) -> IcpResult: ...


@dataclass(frozen=True)
class GlobalAnswer:
    """One answer of the global match."""

    transform: Array  # (4, 4) T_target_source, unit frame
    # The mutually consistent feature matches it rests on (KISS-Matcher's final inliers); 0: not counted (RANSAC's
    # inlier count is of another kind). Enough of them make the answer ``converged`` (``core.confidence.certify``).
    matches: int = 0


# global_match(source_unit (N, 3), target_unit (M, 3), resolution (unit frame), seed, viewpoint (3,): the input
# frame's origin in the unit frame, where the sensor was) -> answers from any initial pose, cheapest first, each
# computed when asked for (none when it finds no answer).
GlobalMatchFn = Callable[[Array, Array, Resolution, int, Array], Iterable[GlobalAnswer]]
# polish(source_unit, target_unit, T_target_source (4, 4), resolution) -> a finer T_target_source, or None where
# the data does not suit it: the last refinement of the winning candidate only.
PolishFn = Callable[[Array, Array, Array, Resolution], "Array | None"]


@dataclass(frozen=True)
class Candidate:
    """One estimate competing to be the result, in the unit frame."""

    confidence: Confidence
    name: str  # one of CANDIDATES
    T_unit: Array  # (4, 4) T_target_source, unit frame
    refined: IcpResult | None  # the ICP that produced it, if any
    agent_index: int | None = None  # which agent run it came from; None for the classical candidates

    def beats(self, other: Candidate | None) -> bool:
        """Whether this candidate ranks above ``other`` (``Confidence.outranks``)."""
        return other is None or self.confidence.outranks(other.confidence)


@dataclass(frozen=True)
class Deferred:
    """A doubtful candidate waiting, part-refined, for its turn (``RegistrationConfig.defer_doubtful``)."""

    name: str  # one of CANDIDATES
    T_unit: Array  # (4, 4) the estimate as offered, unit frame
    part_refined: Array  # (4, 4) after the ICP gate's iterations
    quick: float  # its quick confidence there: the waiting ones are refined best first
    agent_index: int | None = None
    steps: int | None = None  # an agent estimate's steps at its exit check
    matches: int = 0  # a global answer's feature matches (``GlobalAnswer.matches``)


@dataclass
class Registration:
    T_target_source: Array  # (4, 4) the result in world units: target ≈ R @ source + t
    agent_T_target_source: Array  # (4, 4) the agent's own estimate (before ICP), world units
    trajectory: list[tuple[int, str, Array]]  # (step, action name, T_target_source in world units)
    icp: IcpResult | None  # in world units (inlier_rmse scaled back)
    timing_ms: dict[str, float] = field(default_factory=dict)
    agent: AgentResult | None = None
    normalization: Normalization | None = None
    n_source: int = 0
    n_target: int = 0
    confidence: Confidence | None = None  # of ``T_target_source``, unit frame
    init: str = "identity"
    initial_transform: Array = field(default_factory=lambda: np.eye(4))  # (4, 4) the agent's start, world units
    start_index: int = 0  # global mode: which start rotation won
    start_scores: list[float] = field(default_factory=list)  # global mode: each start's agent-only confidence
    checks: list[tuple[int, float]] = field(default_factory=list)  # exit checks: (agent steps, ICP confidence)
    candidate: str = AGENT  # which candidate won (CANDIDATES)
    candidates: dict[str, float] = field(default_factory=dict)  # every candidate tried -> its best confidence
    resolution: Resolution | None = None  # the data's resolution, world units
    n_used: tuple[int, int] = (0, 0)  # points of (source, target) the registration worked on (after the cap)
    network_calls: int = 0  # source poses the reward network scored (full and match-only calls; head-only ones not)

    @property
    def rescued(self) -> str | None:
        """Which rescue won over the agent's result (``None``: the agent's own result won)."""
        return self.candidate if self.candidate in RESCUES else None
