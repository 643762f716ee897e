"""The registration pipeline, runtime-agnostic: clouds in -> preprocess -> agent -> world frame -> ICP.

``register`` is what the service runs per request and what ``pranet-eval`` measures as pranet-v1
(``icp=None``) and pranet-v2. The reward model and the ICP refinement are injected.

``init="identity"`` (the paper's setting) runs the agent once from the input pose. ``init="global"``
runs it from ``n_starts`` well-spread start rotations at once (``core.starts``; one batched score call
per step), ranks the results by their confidence, refines the best ``refine_top`` with ICP and keeps
the most confident: for initial rotations beyond the 60° the model was trained on. Every result
carries a ``Confidence`` (``core.confidence``), computed in the unit frame.

Beyond the paper, with ICP (identity mode): ``exit_checks`` refines the agent's estimate with ICP
after those many steps and returns as soon as the refined result is confident (most pairs need only
the coarse phase: ``docs/PERFORMANCE.md``). When the result stays unconfident, ``rescue_icp`` runs one
wide-window ICP from the input pose and ``rescue_restarts`` reruns the coarse phase from six starts 30°
around the best estimate (batched); the most confident result wins.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np
import numpy.typing as npt

from pranet.core.actions import ActionTable
from pranet.core.agent import AgentResult, BatchScoreFn, ScoreFn, batch_from_single, run_agent, run_agent_batch
from pranet.core.confidence import DEFAULT_THRESHOLD, Confidence, ConfidenceEstimator
from pranet.core.preprocess import Normalization, check_cloud, fit_normalization, resample
from pranet.core.se3 import Array
from pranet.core.starts import DEFAULT_STARTS, local_rotations, restart_transforms, start_rotations, start_transforms

INITS = ("identity", "global")
DEFAULT_REFINE_TOP = 3  # global mode: starts refined by ICP, best first by their agent-only confidence
RANK_SOURCE, RANK_TARGET = 256, 1024
# The service's exit checks: ICP + confidence after the coarse phase and halfway through the fine one.
DEFAULT_EXIT_CHECKS = (20, 40)  # subsample sizes of the quick confidence that ranks the starts


class Scorer(Protocol):
    """What the pipeline needs of a reward model (``pranet.model.runtime.RewardModel`` is one)."""

    table: ActionTable
    schedule: tuple[int, ...]
    n_points: int

    def score_fn(self, target: npt.ArrayLike) -> ScoreFn: ...


def batch_score_fn(scorer: Scorer, target: npt.ArrayLike) -> BatchScoreFn:
    """The scorer's own ``batch_score_fn(target)`` when it has one (one runtime call per step for all
    starts), else its ``score_fn`` called once per start."""
    batched = getattr(scorer, "batch_score_fn", None)
    return batched(target) if batched is not None else batch_from_single(scorer.score_fn(target))


@dataclass(frozen=True)
class IcpResult:
    transform: Array  # (4, 4) T_target_source, unit frame
    fitness: float
    inlier_rmse: float  # unit frame


# icp(source_unit (N, 3), target_unit (M, 3), init T_target_source (4, 4)) -> IcpResult, all in the unit frame.
IcpFn = Callable[[Array, Array, Array], IcpResult]


def split_schedule(schedule: Sequence[int], checks: Sequence[int]) -> list[tuple[int, ...]]:
    """Cut ``schedule`` (steps per scale) after each cumulative step count in ``checks``.

    ``split_schedule((20, 40), (20, 40)) == [(20, 0), (0, 20), (0, 20)]``; checks outside
    ``(0, sum(schedule))`` are ignored. Running the segments one after the other from the previous
    segment's result takes the same steps as running ``schedule`` at once.
    """
    total = sum(schedule)
    cuts = sorted({int(c) for c in checks if 0 < int(c) < total}) + [total]
    segments: list[tuple[int, ...]] = []
    done = 0
    for cut in cuts:
        seg, start = [], 0
        for n in schedule:  # steps of each scale that fall in [done, cut)
            lo, hi = max(start, done), min(start + n, cut)
            seg.append(max(0, hi - lo))
            start += n
        segments.append(tuple(seg))
        done = cut
    return segments


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
    confidence: Confidence | None = None  # of ``transform``, unit frame
    init: str = "identity"
    initial_transform: Array = field(default_factory=lambda: np.eye(4))  # (4, 4) the agent's start, world units
    start_index: int = 0  # global mode: which start rotation won
    start_scores: list[float] = field(default_factory=list)  # global mode: each start's agent-only confidence
    checks: list[tuple[int, float]] = field(default_factory=list)  # exit checks: (agent steps, ICP confidence)
    rescued: str | None = None  # which rescue won over the agent's result: "wide_icp" or "restarts"


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
    init: str = "identity",
    n_starts: int = DEFAULT_STARTS,
    refine_top: int = DEFAULT_REFINE_TOP,
    confidence_threshold: float = DEFAULT_THRESHOLD,
    exit_checks: Sequence[int] = (),
    rescue_icp: IcpFn | None = None,
    rescue_restarts: bool = False,
) -> Registration:
    """Register ``source: (N, 3)`` onto ``target: (M, 3)`` (any units); returns ``T_target_source``.

    ``init``: ``"identity"`` or ``"global"`` (``n_starts`` start rotations, the ``refine_top`` most
    confident refined by ``icp``). Raises ``DegenerateCloudError`` (a ``ValueError``) for unusable
    input and ``AgentTimeout`` past ``deadline`` (``time.monotonic()`` seconds).

    ``exit_checks`` (identity mode with ``icp``): after each of these cumulative step counts, refine
    with ``icp`` and stop once the confidence reaches ``confidence_threshold``; the most confident
    refined estimate is returned. Rescues (with ``icp``), when the result is below the threshold:
    ``rescue_icp`` refines the input pose by ``rescue_icp`` then ``icp``; ``rescue_restarts`` runs the
    coarse phase from ``core.starts.local_rotations`` around the best estimate and refines the
    ``refine_top`` most promising; the most confident result wins.
    """
    if init not in INITS:
        raise ValueError(f"unknown init {init!r}; choose from {INITS}")
    timing: dict[str, float] = {}
    t0 = time.perf_counter()
    # 1. Validate, normalise to the unit frame (one similarity for both clouds), resample to the model's N.
    src = check_cloud(source, "source")
    tgt = check_cloud(target, "target")
    norm = fit_normalization(src, tgt)
    src_unit, tgt_unit = norm.to_unit(src), norm.to_unit(tgt)
    src_n = resample(src_unit, scorer.n_points, rng)
    tgt_n = resample(tgt_unit, scorer.n_points, rng)
    schedule = schedule or scorer.schedule
    t1 = time.perf_counter()
    timing["preprocess"] = (t1 - t0) * 1e3
    # 2. Embed the target once for this registration (tiled over the starts in global mode).
    score_fn = scorer.score_fn(tgt_n) if init == "identity" else batch_score_fn(scorer, tgt_n)
    t2 = time.perf_counter()
    timing["target_embedding"] = (t2 - t1) * 1e3
    # 3. The greedy action loop (20 coarse + 40 fine steps by default), from one start or from each start.
    loop: dict = {"policy": policy, "rng": rng, "early_stop": early_stop, "deadline": deadline}
    estimator = ConfidenceEstimator(tgt_unit, threshold=confidence_threshold)
    checked: list[tuple[Confidence, IcpResult]] = []  # exit checks' refined estimates, in step order
    checks: list[tuple[int, float]] = []
    check_ms = [0.0, 0.0]  # ICP, confidence
    if init == "identity" and icp is not None and exit_checks:
        starts = np.eye(4)[None]
        agent = AgentResult(transform=np.eye(4))
        segments = split_schedule(schedule, exit_checks)
        for k, segment in enumerate(segments):
            part = run_agent(src_n, tgt_n, score_fn, scorer.table, segment, initial_transform=agent.transform, **loop)
            n = len(agent.steps)
            agent.steps += [replace(s, step=s.step + n) for s in part.steps]
            agent.stopped_early += [i + n for i in part.stopped_early]
            agent.transform = part.transform
            if k == len(segments) - 1:
                break
            t_icp = time.perf_counter()
            refined = icp(src_unit, tgt_unit, agent.transform)
            t_conf = time.perf_counter()
            confidence = estimator.evaluate(src_unit, refined.transform)
            check_ms[0] += (t_conf - t_icp) * 1e3
            check_ms[1] += (time.perf_counter() - t_conf) * 1e3
            checked.append((confidence, refined))
            checks.append((len(agent.steps), confidence.score))
            if confidence.score >= confidence_threshold:
                break
        agents = [agent]
    elif init == "identity":
        starts = np.eye(4)[None]  # (1, 4, 4)
        agents = [run_agent(src_n, tgt_n, score_fn, scorer.table, schedule, **loop)]
    else:
        starts = start_transforms(start_rotations(n_starts), src_n.mean(axis=0), tgt_unit.mean(axis=0))  # (B, 4, 4)
        agents = run_agent_batch(src_n, tgt_n, score_fn, scorer.table, starts, schedule, **loop)
    t3 = time.perf_counter()
    timing["agent_steps"] = (t3 - t2) * 1e3 - sum(check_ms)
    # 4. Global mode: rank the starts by a quick confidence of the agent's result; keep the best few.
    start_scores: list[float] = []
    candidates = [0]
    if init == "global":
        ranker = ConfidenceEstimator(tgt_unit, max_target=RANK_TARGET, threshold=confidence_threshold)
        start_scores = [ranker.evaluate(src_unit, a.transform, max_source=RANK_SOURCE).score for a in agents]
        order = np.argsort(-np.asarray(start_scores), kind="stable")
        candidates = [int(b) for b in order[: max(1, refine_top) if icp is not None else 1]]
    # 5. Optional ICP refinement on the full clouds (PRANet-v2); the most confident candidate wins.
    #    With exit checks, the last check (if it stopped the loop) is the final refinement already.
    best: tuple[Confidence, int, Array, IcpResult | None] | None = None
    for confidence, refined in checked:
        if best is None or confidence.score > best[0].score:
            best = (confidence, 0, refined.transform, refined)
    icp_ms = check_ms[0]
    stopped_at_check = bool(checks) and checks[-1][0] == len(agents[0].steps)
    for b in [] if stopped_at_check else candidates:
        t_icp = time.perf_counter()
        refined = icp(src_unit, tgt_unit, agents[b].transform) if icp is not None else None
        icp_ms += (time.perf_counter() - t_icp) * 1e3
        T_unit = refined.transform if refined is not None else agents[b].transform
        confidence = estimator.evaluate(src_unit, T_unit)
        if best is None or confidence.score > best[0].score:
            best = (confidence, b, T_unit, refined)
    assert best is not None
    # 6. Rescues of an unconfident result (beyond the paper): a wide ICP from the input pose, then restarts.
    t_rescue = time.perf_counter()
    rescued: str | None = None
    suspect = best[0].score < confidence_threshold  # both rescues run: a wide ICP may be confidently wrong
    if icp is not None and rescue_icp is not None and suspect:
        wide = icp(src_unit, tgt_unit, rescue_icp(src_unit, tgt_unit, np.eye(4)).transform)
        confidence = estimator.evaluate(src_unit, wide.transform)
        if confidence.score > best[0].score:
            best, rescued = (confidence, best[1], wide.transform, wide), "wide_icp"
    if icp is not None and rescue_restarts and suspect:
        restarts = restart_transforms(best[2], src_n.mean(axis=0), local_rotations())
        coarse = (schedule[0],) + (0,) * (len(schedule) - 1)
        more = run_agent_batch(src_n, tgt_n, batch_score_fn(scorer, tgt_n), scorer.table, restarts, coarse, **loop)
        ranker = ConfidenceEstimator(tgt_unit, max_target=RANK_TARGET, threshold=confidence_threshold)
        quick = [ranker.evaluate(src_unit, a.transform, max_source=RANK_SOURCE).score for a in more]
        for k in np.argsort(-np.asarray(quick), kind="stable")[: max(1, refine_top)]:
            refined = icp(src_unit, tgt_unit, more[k].transform)
            confidence = estimator.evaluate(src_unit, refined.transform)
            if confidence.score > best[0].score:
                best, rescued = (confidence, len(agents) + int(k), refined.transform, refined), "restarts"
        agents = [*agents, *more]
        starts = np.concatenate([starts, restarts])
    rescue_ms = (time.perf_counter() - t_rescue) * 1e3
    confidence, b, T_unit, refined = best
    timing["icp"] = icp_ms
    # After the loop: everything but its ICP calls; plus the exit checks' confidence (their ICP is in icp_ms).
    timing["confidence"] = (t_rescue - t3) * 1e3 - (icp_ms - check_ms[0]) + check_ms[1]  # ranking the starts included
    timing["rescue"] = rescue_ms
    # 6. Back to world units.
    agent = agents[b]
    result_T = norm.transform_to_world(T_unit)
    icp_world = IcpResult(result_T, refined.fitness, refined.inlier_rmse / norm.scale) if refined else None
    timing["total"] = (time.perf_counter() - t0) * 1e3
    trajectory = [(s.step, s.name, norm.transform_to_world(s.transform)) for s in agent.steps]
    return Registration(
        transform=result_T,
        agent_transform=norm.transform_to_world(agent.transform),
        trajectory=trajectory,
        icp=icp_world,
        timing_ms=timing,
        agent=agent,
        normalization=norm,
        n_source=len(src),
        n_target=len(tgt),
        confidence=confidence,
        init=init,
        initial_transform=norm.transform_to_world(starts[b]),
        start_index=b,
        start_scores=start_scores,
        checks=checks,
        rescued=rescued,
    )
