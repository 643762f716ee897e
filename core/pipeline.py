"""The registration pipeline, runtime-agnostic: clouds in -> prepare -> agent (with exit checks) -> rank ->
refine -> rescue -> back to world units.

``register`` runs one registration as a ``RegistrationConfig`` (``core.registration_config``) says: the paper's
PRANet-v1 (no ICP), PRANet-v2 (+ ICP), or the service's default (exit checks and rescues). The reward model and
the ICP functions are injected (``pranet.engine`` builds them from the config), so this module stays numpy-only.

``init="identity"`` (the paper's setting) runs the agent once from the input pose. ``init="global"`` runs its
coarse phase from ``n_starts`` well-spread start rotations at once (``core.starts``; one batched score call per
step), the fine phase from the ``refine_top`` most confident, and refines those with ICP: for initial rotations
beyond the 60° the model was trained on. Every result carries a ``Confidence`` (``core.confidence``),
computed in the unit frame.

Beyond the paper, with ICP (identity mode): exit checks refine the agent's estimate after some steps and return
as soon as the refined result is confident (most pairs need only the coarse phase: ``docs/PERFORMANCE.md``).
When the result stays unconfident, the rescues run: a wide-window ICP from the input pose, and the coarse phase
again from six starts 30° around the best estimate (batched); the most confident result wins.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Protocol

import numpy as np
import numpy.typing as npt

from pranet.core.actions import ActionTable
from pranet.core.agent import AgentResult, BatchScoreFn, ScoreFn, batch_from_single, run_agent, run_agent_batch
from pranet.core.confidence import Confidence, ConfidenceEstimator
from pranet.core.preprocess import Normalization, check_cloud, fit_normalization, resample
from pranet.core.registration_config import PAPER_V1, RegistrationConfig
from pranet.core.se3 import Array
from pranet.core.starts import local_rotations, restart_transforms, start_rotations, start_transforms

RANK_SOURCE, RANK_TARGET = 256, 1024  # subsample sizes of the quick confidence that ranks the starts


class Scorer(Protocol):
    """What the pipeline needs of a reward model (``pranet.engine.runtime.RewardModel`` is one)."""

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
    rescued: str | None = None  # which rescue won over the agent's result: "wide_icp" or "restarts"


@dataclass(frozen=True)
class Candidate:
    """One estimate competing to be the result, in the unit frame."""

    confidence: Confidence
    agent_index: int  # which agent run (start) it came from
    T_unit: Array  # (4, 4) T_target_source, unit frame
    refined: IcpResult | None  # the ICP that produced it, if any
    rescued: str | None = None


def _better(best: Candidate | None, other: Candidate) -> Candidate:
    return other if best is None or other.confidence.score > best.confidence.score else best


@dataclass
class _Prepared:
    """The clouds of one registration: checked, in the unit frame, and resampled to the model's N."""

    source: Array  # (Ns, 3) as given
    target: Array  # (Nt, 3)
    norm: Normalization
    src_unit: Array  # (Ns, 3)
    tgt_unit: Array  # (Nt, 3)
    src_n: Array  # (N, 3)
    tgt_n: Array  # (N, 3)

    @cached_property
    def ranker(self) -> ConfidenceEstimator:
        """The quick confidence (subsampled target) that ranks starts: built once, on first use."""
        return ConfidenceEstimator(self.tgt_unit, max_target=RANK_TARGET)


@dataclass
class _AgentRuns:
    starts: Array  # (B, 4, 4) unit-frame start transforms
    agents: list[AgentResult]
    checked: list[Candidate]  # exit checks' refined estimates, in step order
    checks: list[tuple[int, float]]
    check_ms: list[float]  # [ICP, confidence] time spent in the exit checks


def prepare(source: npt.ArrayLike, target: npt.ArrayLike, n_points: int, rng: np.random.Generator) -> _Prepared:
    """Validate, normalise to the unit frame (one similarity for both clouds), resample to the model's N."""
    src = check_cloud(source, "source")
    tgt = check_cloud(target, "target")
    norm = fit_normalization(src, tgt)
    src_unit, tgt_unit = norm.to_unit(src), norm.to_unit(tgt)
    return _Prepared(
        src, tgt, norm, src_unit, tgt_unit, resample(src_unit, n_points, rng), resample(tgt_unit, n_points, rng)
    )


def run_agents(
    p: _Prepared,
    scorer: Scorer,
    score_fn: ScoreFn | BatchScoreFn,
    config: RegistrationConfig,
    schedule: Sequence[int],
    loop: dict,
    estimator: ConfidenceEstimator,
    icp: IcpFn | None,
) -> _AgentRuns:
    """The greedy action loop (20 coarse + 40 fine steps by default): from the input pose, with exit checks
    when ICP is on and the config has them, or from every global start at once."""
    if config.init == "global":
        starts = start_transforms(start_rotations(config.n_starts), p.src_n.mean(axis=0), p.tgt_unit.mean(axis=0))
        return _AgentRuns(starts, run_global(p, scorer, score_fn, config, schedule, loop, starts), [], [], [0.0, 0.0])
    starts = np.eye(4)[None]  # (1, 4, 4)
    if icp is None or not config.exit_checks:
        return _AgentRuns(
            starts, [run_agent(p.src_n, p.tgt_n, score_fn, scorer.table, schedule, **loop)], [], [], [0.0, 0.0]
        )
    runs = _AgentRuns(starts, [AgentResult(transform=np.eye(4))], [], [], [0.0, 0.0])
    agent = runs.agents[0]
    segments = split_schedule(schedule, config.exit_checks)
    for k, segment in enumerate(segments):
        part = run_agent(p.src_n, p.tgt_n, score_fn, scorer.table, segment, initial_transform=agent.transform, **loop)
        extend(agent, part)
        if k == len(segments) - 1:
            break
        # The exit check: refine now and stop if confident.
        t_icp = time.perf_counter()
        refined = icp(p.src_unit, p.tgt_unit, agent.transform)
        t_conf = time.perf_counter()
        confidence = estimator.evaluate(p.src_unit, refined.transform)
        runs.check_ms[0] += (t_conf - t_icp) * 1e3
        runs.check_ms[1] += (time.perf_counter() - t_conf) * 1e3
        runs.checked.append(Candidate(confidence, 0, refined.transform, refined))
        runs.checks.append((len(agent.steps), confidence.score))
        if confidence.score >= config.threshold:
            break
    return runs


def run_global(
    p: _Prepared,
    scorer: Scorer,
    score_fn: ScoreFn | BatchScoreFn,
    config: RegistrationConfig,
    schedule: Sequence[int],
    loop: dict,
    starts: Array,
) -> list[AgentResult]:
    """Global mode: the coarse phase from every start at once (batched), then the rest of the schedule from the
    ``refine_top`` most confident only: the fine phase polishes, it does not decide which start wins, and each
    start costs a score call per step. The others keep their coarse-phase result."""
    segments = split_schedule(schedule, (schedule[0],))
    agents = run_agent_batch(p.src_n, p.tgt_n, score_fn, scorer.table, starts, segments[0], **loop)
    if len(segments) == 1:
        return agents
    order = np.argsort(-np.asarray(quick_scores(p, agents)), kind="stable")
    keep = [int(b) for b in order[: config.refine_top]]
    pose = np.stack([agents[b].transform for b in keep])
    more = run_agent_batch(p.src_n, p.tgt_n, score_fn, scorer.table, pose, segments[1], **loop)
    for b, part in zip(keep, more, strict=True):
        extend(agents[b], part)
    return agents


def extend(agent: AgentResult, part: AgentResult) -> None:
    """Append ``part``, run from where ``agent`` ended, to ``agent`` (steps numbered on)."""
    n = len(agent.steps)
    agent.steps += [replace(s, step=s.step + n) for s in part.steps]
    agent.stopped_early += [i + n for i in part.stopped_early]
    agent.transform = part.transform


def quick_scores(p: _Prepared, agents: Sequence[AgentResult]) -> list[float]:
    """A quick confidence of each agent's result (subsampled clouds): to rank starts before refining them."""
    return [p.ranker.evaluate(p.src_unit, a.transform, max_source=RANK_SOURCE).score for a in agents]


def rank_starts(
    p: _Prepared, agents: Sequence[AgentResult], config: RegistrationConfig, refining: bool
) -> tuple[list[int], list[float]]:
    """Global mode: the agents' results ranked by a quick confidence -> (the ones to refine, every start's score)."""
    if config.init != "global":
        return [0], []
    scores = quick_scores(p, agents)
    order = np.argsort(-np.asarray(scores), kind="stable")
    return [int(b) for b in order[: config.refine_top if refining else 1]], scores


def refine(
    p: _Prepared,
    runs: _AgentRuns,
    candidates: Sequence[int],
    estimator: ConfidenceEstimator,
    icp: IcpFn | None,
) -> tuple[Candidate, float]:
    """ICP on the candidates (PRANet-v2); the most confident of them and of the exit checks wins.
    Returns it and the ICP time (ms). When the last exit check stopped the loop, it is the final refinement."""
    best: Candidate | None = None
    for c in runs.checked:
        best = _better(best, c)
    icp_ms = 0.0
    stopped_at_check = bool(runs.checks) and runs.checks[-1][0] == len(runs.agents[0].steps)
    for b in [] if stopped_at_check else candidates:
        t_icp = time.perf_counter()
        refined = icp(p.src_unit, p.tgt_unit, runs.agents[b].transform) if icp is not None else None
        icp_ms += (time.perf_counter() - t_icp) * 1e3
        T_unit = refined.transform if refined is not None else runs.agents[b].transform
        best = _better(best, Candidate(estimator.evaluate(p.src_unit, T_unit), b, T_unit, refined))
    assert best is not None
    return best, icp_ms


def rescue(
    p: _Prepared,
    best: Candidate,
    runs: _AgentRuns,
    scorer: Scorer,
    config: RegistrationConfig,
    schedule: Sequence[int],
    loop: dict,
    estimator: ConfidenceEstimator,
    icp: IcpFn,
    rescue_icp: IcpFn | None,
) -> Candidate:
    """Rescues of an unconfident result (beyond the paper): a wide ICP from the input pose, then the coarse phase
    from six starts 30° around the best estimate. Both run when suspect: a wide ICP may be confidently wrong.
    The restarts' agent runs are appended to ``runs``."""
    if rescue_icp is not None:
        wide = icp(p.src_unit, p.tgt_unit, rescue_icp(p.src_unit, p.tgt_unit, np.eye(4)).transform)
        wide_c = Candidate(
            estimator.evaluate(p.src_unit, wide.transform), best.agent_index, wide.transform, wide, "wide_icp"
        )
        best = _better(best, wide_c)
    if config.rescue_restarts:
        restarts = restart_transforms(best.T_unit, p.src_n.mean(axis=0), local_rotations())
        coarse = (schedule[0],) + (0,) * (len(schedule) - 1)
        batch = batch_score_fn(scorer, p.tgt_n)
        more = run_agent_batch(p.src_n, p.tgt_n, batch, scorer.table, restarts, coarse, **loop)
        quick = quick_scores(p, more)
        for k in np.argsort(-np.asarray(quick), kind="stable")[: config.refine_top]:
            refined = icp(p.src_unit, p.tgt_unit, more[k].transform)
            index = len(runs.agents) + int(k)
            best = _better(
                best,
                Candidate(
                    estimator.evaluate(p.src_unit, refined.transform), index, refined.transform, refined, "restarts"
                ),
            )
        runs.agents.extend(more)
        runs.starts = np.concatenate([runs.starts, restarts])
    return best


def register(
    source: npt.ArrayLike,
    target: npt.ArrayLike,
    scorer: Scorer,
    rng: np.random.Generator,
    config: RegistrationConfig = PAPER_V1,
    icp: IcpFn | None = None,
    rescue_icp: IcpFn | None = None,
    deadline: float | None = None,
) -> Registration:
    """Register ``source: (N, 3)`` onto ``target: (M, 3)`` (any units) as ``config`` says; returns
    ``T_target_source`` (target ≈ R @ source + t) and the agent's own estimate, both in world units.

    ``icp``: the refinement (``None`` = PRANet-v1, whatever ``config.icp_stages`` say: the engine builds it from
    them); ``rescue_icp``: the wide ICP of the rescue (``None`` = off). Raises ``DegenerateCloudError`` (a
    ``ValueError``) for unusable input and ``AgentTimeout`` past ``deadline`` (``time.monotonic()`` seconds).
    """
    timing: dict[str, float] = {}
    t0 = time.perf_counter()
    # 1. Prepare: validate, unit frame, resample.
    p = prepare(source, target, scorer.n_points, rng)
    schedule = config.schedule or scorer.schedule
    t1 = time.perf_counter()
    timing["preprocess"] = (t1 - t0) * 1e3
    # 2. Embed the target once for this registration (tiled over the starts in global mode).
    score_fn = scorer.score_fn(p.tgt_n) if config.init == "identity" else batch_score_fn(scorer, p.tgt_n)
    t2 = time.perf_counter()
    timing["target_embedding"] = (t2 - t1) * 1e3
    # 3. The agent, with exit checks.
    loop = {"policy": config.policy, "rng": rng, "early_stop": config.early_stop, "deadline": deadline}
    estimator = ConfidenceEstimator(p.tgt_unit, threshold=config.threshold)
    runs = run_agents(p, scorer, score_fn, config, schedule, loop, estimator, icp)
    t3 = time.perf_counter()
    timing["agent_steps"] = (t3 - t2) * 1e3 - sum(runs.check_ms)
    # 4. Rank the global starts; 5. refine the best with ICP.
    candidates, start_scores = rank_starts(p, runs.agents, config, refining=icp is not None)
    best, icp_ms = refine(p, runs, candidates, estimator, icp)
    icp_ms += runs.check_ms[0]
    # 6. Rescue an unconfident result.
    t_rescue = time.perf_counter()
    if icp is not None and best.confidence.score < config.threshold:
        best = rescue(p, best, runs, scorer, config, schedule, loop, estimator, icp, rescue_icp)
    timing["icp"] = icp_ms
    # After the loop: everything but its ICP calls; plus the exit checks' confidence (their ICP is in icp_ms).
    timing["confidence"] = (t_rescue - t3) * 1e3 - (icp_ms - runs.check_ms[0]) + runs.check_ms[1]
    timing["rescue"] = (time.perf_counter() - t_rescue) * 1e3
    # 7. Back to world units.
    return _to_world(p, runs, best, start_scores, config, timing, t0)


def _to_world(
    p: _Prepared,
    runs: _AgentRuns,
    best: Candidate,
    start_scores: list[float],
    config: RegistrationConfig,
    timing: dict[str, float],
    t0: float,
) -> Registration:
    norm = p.norm
    agent = runs.agents[best.agent_index]
    T = norm.transform_to_world(best.T_unit)
    refined = best.refined
    icp_world = IcpResult(T, refined.fitness, refined.inlier_rmse / norm.scale) if refined else None
    timing["total"] = (time.perf_counter() - t0) * 1e3
    return Registration(
        T_target_source=T,
        agent_T_target_source=norm.transform_to_world(agent.transform),
        trajectory=[(s.step, s.name, norm.transform_to_world(s.transform)) for s in agent.steps],
        icp=icp_world,
        timing_ms=timing,
        agent=agent,
        normalization=norm,
        n_source=len(p.source),
        n_target=len(p.target),
        confidence=best.confidence,
        init=config.init,
        initial_transform=norm.transform_to_world(runs.starts[best.agent_index]),
        start_index=best.agent_index,
        start_scores=start_scores,
        checks=runs.checks,
        rescued=best.rescued,
    )
