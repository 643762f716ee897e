"""The registration pipeline, runtime-agnostic: clouds in -> preprocess -> agent -> world frame -> ICP.

``register`` is what the service runs per request and what ``pranet-eval`` measures as pranet-v1
(``icp=None``) and pranet-v2. The reward model and the ICP refinement are injected.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from pranet.core.actions import ActionTable
from pranet.core.agent import AgentResult, ScoreFn, run_agent
from pranet.core.preprocess import Normalization, check_cloud, fit_normalization, resample
from pranet.core.se3 import Array


class Scorer(Protocol):
    """What the pipeline needs of a reward model (``pranet.model.runtime.RewardModel`` is one)."""

    table: ActionTable
    schedule: tuple[int, ...]
    n_points: int

    def score_fn(self, target: npt.ArrayLike) -> ScoreFn: ...


@dataclass(frozen=True)
class IcpResult:
    transform: Array  # (4, 4) T_target_source, unit frame
    fitness: float
    inlier_rmse: float  # unit frame


# icp(source_unit (N, 3), target_unit (M, 3), init T_target_source (4, 4)) -> IcpResult, all in the unit frame.
IcpFn = Callable[[Array, Array, Array], IcpResult]


@dataclass
class Registration:
    transform: Array  # (4, 4) T_target_source in world units: target ≈ R @ source + t
    agent_transform: Array  # (4, 4) before ICP, world units
    trajectory: list[tuple[int, str, Array]]  # (step, action name, T_target_source in world units)
    icp: IcpResult | None  # in world units (inlier_rmse scaled back)
    timing_ms: dict[str, float] = field(default_factory=dict)
    agent: AgentResult | None = None
    normalization: Normalization | None = None
    n_source: int = 0
    n_target: int = 0


def register(
    source: npt.ArrayLike,
    target: npt.ArrayLike,
    scorer: Scorer,
    rng: np.random.Generator,
    icp: IcpFn | None = None,
    policy: str = "deterministic",
    early_stop: bool = False,
    schedule: Sequence[int] | None = None,
    deadline: float | None = None,
) -> Registration:
    """Register ``source: (N, 3)`` onto ``target: (M, 3)`` (any units); returns ``T_target_source``.

    Raises ``DegenerateCloudError`` (a ``ValueError``) for unusable input and ``AgentTimeout`` past
    ``deadline`` (``time.monotonic()`` seconds).
    """
    timing: dict[str, float] = {}
    t0 = time.perf_counter()
    # 1. Validate, normalise to the unit frame (one similarity for both clouds), resample to the model's N.
    src = check_cloud(source, "source")
    tgt = check_cloud(target, "target")
    norm = fit_normalization(src, tgt)
    src_unit, tgt_unit = norm.to_unit(src), norm.to_unit(tgt)
    src_n = resample(src_unit, scorer.n_points, rng)
    tgt_n = resample(tgt_unit, scorer.n_points, rng)
    t1 = time.perf_counter()
    timing["preprocess"] = (t1 - t0) * 1e3
    # 2. Embed the target once for this registration.
    score_fn = scorer.score_fn(tgt_n)
    t2 = time.perf_counter()
    timing["target_embedding"] = (t2 - t1) * 1e3
    # 3. The greedy action loop (20 coarse + 40 fine steps by default).
    agent = run_agent(
        src_n,
        tgt_n,
        score_fn,
        scorer.table,
        schedule or scorer.schedule,
        policy=policy,
        rng=rng,
        early_stop=early_stop,
        deadline=deadline,
    )
    t3 = time.perf_counter()
    timing["agent_steps"] = (t3 - t2) * 1e3
    # 4. Back to world units; optional ICP refinement on the full clouds (PRANet-v2).
    agent_T = norm.transform_to_world(agent.transform)
    result_T = agent_T
    icp_world: IcpResult | None = None
    if icp is not None:
        refined = icp(src_unit, tgt_unit, agent.transform)
        result_T = norm.transform_to_world(refined.transform)
        icp_world = IcpResult(result_T, refined.fitness, refined.inlier_rmse / norm.scale)
    timing["icp"] = (time.perf_counter() - t3) * 1e3
    timing["total"] = (time.perf_counter() - t0) * 1e3
    trajectory = [(s.step, s.name, norm.transform_to_world(s.transform)) for s in agent.steps]
    return Registration(
        transform=result_T,
        agent_transform=agent_T,
        trajectory=trajectory,
        icp=icp_world,
        timing_ms=timing,
        agent=agent,
        normalization=norm,
        n_source=len(src),
        n_target=len(tgt),
    )
