"""The registration pipeline, runtime-agnostic: a set of candidates ranked by one confidence.

    clouds in -> prepare (check, cap, unit frame, resolution) -> agent from the input pose (exit checks)
      -> global match (features + robust solver) -> rescues (agent restarts, shifted ICP starts, wide ICP, the agent
      from the global mode's starts, ICP from turned copies of the best) -> the winner's finish -> back to world units

``register`` runs one registration as a ``RegistrationConfig`` (``core.registration_config``) says: the paper's
PRANet-v1 (the agent alone), PRANet-v2 (+ ICP), or the service's default. Cheap candidates come first and a
confident result ends the request: the agent's exit checks refine its estimate with ICP at the data's own
resolution after 20 and 40 steps and stop once ``converged`` (before the global match, once sure: at least
``exit_confidence``); only a result short of that pays for the global match, and only a still unconfident one for
the rescues. Every candidate is refined by the same ICP and scored by
the same ``Confidence`` (``core.confidence``); the most confident wins and the response names it.

``init="global"`` forces the wide search: the agent's coarse phase from ``n_starts`` well-spread rotations at once
(``core.starts``; one batched score call per step), the fine phase from the ``refine_top`` most confident, and
the global match beside them.

The reward model, the ICP and the global match are injected (``pranet.engine`` builds them), so this module stays
numpy-only. The state of one registration lives on a ``RegistrationContext``; the stages' times on its
``StageTimer``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import numpy.typing as npt

from pranet.core.agent import AgentResult, BatchScoreFn, ScoreFn, batch_from_single, run_agent, run_agent_batch
from pranet.core.confidence import ConfidenceEstimator
from pranet.core.registration_config import CENTRED_TURNS, PAPER_V1, TURNS, RegistrationConfig
from pranet.core.registration_context import RegistrationContext, Scorer, prepare
from pranet.core.registration_types import (
    AGENT,
    GLOBAL_MATCH,
    GLOBAL_STARTS,
    RESTARTS,
    SHIFTED_ICP,
    TURNED_ICP,
    WIDE_ICP,
    GlobalMatchFn,
    IcpFn,
    PolishFn,
    Registration,
)
from pranet.core.robust_icp import symmetric_robust_icp
from pranet.core.se3 import Array
from pranet.core.stage_timer import StageTimer
from pranet.core.starts import (
    centred_turned_transforms,
    local_rotations,
    restart_transforms,
    shifted_transforms,
    start_rotations,
    start_transforms,
    turned_transforms,
)

# The finish of sparse partial pairs (``finish_partial_overlap``): for winners with less than this fraction of the
# source near the target (whole-shape pairs: 0.98-1.0; ModelNet40's partial pairs: 0.68-1.0, median 0.87), with
# Tukey's kernel at this many spacings (from the true pose of 150 partial pairs: 131, 136 and 129 right at 1, 1.5
# and 2): docs/DESIGN.md, "A finish for partial overlap".
PARTIAL_OVERLAP = 0.98
FINISH_KERNEL_SPACINGS = 1.5

__all__ = ["register", "prepare", "split_schedule", "batch_score_fn", "STAGES"]

# The stages of ``Registration.timing_ms`` (exclusive: ICP and confidence calls count as themselves wherever they
# run), which with ``other`` (``core.stage_timer``) add up to its ``total``.
STAGES = ("preprocess", "target_embedding", "agent_steps", "icp", "confidence", "global_match", "rescue", "polish")


def batch_score_fn(scorer: Scorer, target: npt.ArrayLike) -> BatchScoreFn:
    """The scorer's own ``batch_score_fn(target)`` when it has one (one runtime call per step for all
    starts), else its ``score_fn`` called once per start."""
    batched = getattr(scorer, "batch_score_fn", None)
    return batched(target) if batched is not None else batch_from_single(scorer.score_fn(target))


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


def extend(agent: AgentResult, part: AgentResult) -> None:
    """Append ``part``, run from where ``agent`` ended, to ``agent`` (steps numbered on)."""
    n = len(agent.steps)
    agent.steps += [replace(s, step=s.step + n) for s in part.steps]
    agent.stopped_early += [i + n for i in part.stopped_early]
    agent.transform = part.transform


# The stages. Each reads the context and offers its candidates to it.


def segments_between(schedule: Sequence[int], checks: Sequence[int], start: int, end: int) -> list[tuple[int, ...]]:
    """The segments of ``schedule`` covering steps ``[start, end)``, cut after each cumulative count in ``checks``.

    ``segments_between((20, 40), (20, 40), 20, 60) == [(0, 20), (0, 20)]``."""
    total = sum(schedule)
    cuts = sorted({int(x) for x in (*checks, start, end) if 0 < int(x) < total})
    segments = split_schedule(schedule, cuts)
    bounds = list(zip([0, *cuts], [*cuts, total], strict=True))
    return [seg for seg, (lo, hi) in zip(segments, bounds, strict=True) if start <= lo and hi <= end]


def _scheduled_ends(start: int, segments: Sequence[tuple[int, ...]]) -> list[int]:
    """The cumulative scheduled step count at the end of each segment (early stops may take fewer steps)."""
    return [start + int(n) for n in np.cumsum([sum(seg) for seg in segments])]


def agent_from_input_pose(ctx: RegistrationContext, score_fn: ScoreFn, until: int | None = None) -> None:
    """The greedy action loop (20 coarse + 40 fine steps by default) from the input pose, or on from where an
    earlier call stopped, up to ``until`` steps in all (``None``: the whole schedule). With ICP and exit checks,
    the estimate is refined and scored after those step counts, and the loop stops once confident; the end of
    the schedule is always refined and scored."""
    c = ctx.clouds
    if not ctx.agents:
        ctx.agents.append(AgentResult(transform=np.eye(4)))
    agent = ctx.agents[0]
    total = sum(ctx.schedule)
    end = total if until is None else min(until, total)
    checks = set(ctx.config.exit_checks) if ctx.icp is not None else set()
    segments = segments_between(ctx.schedule, sorted(checks), ctx.agent_scheduled, end)
    for segment, scheduled in zip(segments, _scheduled_ends(ctx.agent_scheduled, segments), strict=True):
        with ctx.timer.stage("agent_steps"):
            part = run_agent(
                c.src_n,
                c.tgt_n,
                score_fn,
                ctx.scorer.table,
                segment,
                initial_transform=agent.transform,
                **ctx.loop(score_fn),
            )
        extend(agent, part)
        ctx.agent_scheduled = scheduled
        if scheduled in checks and scheduled < total:  # an exit check
            if until is not None:  # before the global match: a doubtful estimate may wait behind it
                checked = ctx.offer_or_defer(AGENT, agent.transform, agent_index=0, steps=len(agent.steps))
                if checked is None:
                    continue  # waits for its turn (offer_deferred)
            else:
                checked = ctx.offer(AGENT, agent.transform, agent_index=0)
            ctx.checks.append((len(agent.steps), checked.confidence.score))
            if ctx.sure if until is not None else ctx.confident:  # before the global match: the surer bar
                return
    if ctx.agent_scheduled == total:
        ctx.offer(AGENT, agent.transform, agent_index=0)


def agent_from_global_starts(ctx: RegistrationContext, score_fn: BatchScoreFn) -> None:
    """Global mode: the coarse phase from every start at once (batched), then the rest of the schedule from the
    ``refine_top`` most confident only: the fine phase polishes, it does not decide which start wins, and each
    start costs a score call per step. The others keep their coarse-phase result.

    With ICP and an exit check at or before the coarse phase's end, the most confident start is refined and scored
    there first, and a ``sure`` result (``RegistrationContext.sure``) ends the search: ICP finishes what the fine
    phase would have polished, and the other starts and the global match could only tie with it."""
    ctx.starts = global_starts(ctx)
    coarse, *fine = split_schedule(ctx.schedule, (ctx.schedule[0],))
    ctx.agents, ctx.start_scores = from_starts(ctx, score_fn, ctx.starts, coarse)
    if coarse_exit_check_is_sure(ctx):
        return
    if fine:
        fine_phase_from_the_best_starts(ctx, score_fn, fine[0])
    for b in _top(ctx.start_scores, ctx.config.refine_top if ctx.icp is not None else 1):
        ctx.offer(AGENT, ctx.agents[b].transform, agent_index=b)


def coarse_exit_check_is_sure(ctx: RegistrationContext) -> bool:
    """Global mode, with ICP and an exit check at or before the coarse phase's end: the most confident start refined
    and scored (recorded in ``ctx.checks``); whether the result is ``sure``."""
    if ctx.icp is None or not any(0 < c <= ctx.schedule[0] for c in ctx.config.exit_checks):
        return False
    b = _top(ctx.start_scores, 1)[0]
    checked = ctx.offer(AGENT, ctx.agents[b].transform, agent_index=b)
    ctx.checks.append((len(ctx.agents[b].steps), checked.confidence.score))
    return ctx.sure


def fine_phase_from_the_best_starts(ctx: RegistrationContext, score_fn: BatchScoreFn, segment: tuple[int, ...]) -> None:
    """The ``refine_top`` most confident starts on through ``segment`` (batched), their runs and scores updated; the
    other starts keep their coarse-phase result and score."""
    keep = _top(ctx.start_scores, ctx.config.refine_top)
    more, scores = from_starts(ctx, score_fn, np.stack([ctx.agents[b].transform for b in keep]), segment)
    for b, part, score in zip(keep, more, scores, strict=True):
        extend(ctx.agents[b], part)
        ctx.start_scores[b] = score


def global_starts(ctx: RegistrationContext) -> Array:
    """The global mode's ``config.n_starts`` well-spread rotations of the source about its centroid, each placed on
    the target's centroid: ``(n_starts, 4, 4)``."""
    c = ctx.clouds
    return start_transforms(start_rotations(ctx.config.n_starts), c.src_n.mean(axis=0), c.tgt_unit.mean(axis=0))


def from_starts(
    ctx: RegistrationContext, score_fn: BatchScoreFn, starts: Array, segment: tuple[int, ...]
) -> tuple[list[AgentResult], list[float]]:
    """The agent from every start at once (batched) through ``segment`` of the schedule; each run and its quick
    confidence."""
    c = ctx.clouds
    with ctx.timer.stage("agent_steps"):
        agents = run_agent_batch(c.src_n, c.tgt_n, score_fn, ctx.scorer.table, starts, segment, **ctx.loop(score_fn))
    return agents, ctx.quick_scores(agents)


def global_match_after(ctx: RegistrationContext) -> int | None:
    """The agent steps after which the global match runs unless the agent is sure: the last exit check of the
    coarse phase (a check before it can only end the request early), or the first check if none is in it; ``None``
    without a global match."""
    checks = ctx.config.exit_checks
    if ctx.global_match is None or not checks:
        return None
    coarse = [c for c in checks if c <= ctx.schedule[0]]
    return max(coarse) if coarse else min(checks)


def _top(scores: Sequence[float], k: int) -> list[int]:
    """The indices of the ``k`` highest ``scores``, best first (ties: the earlier first)."""
    return [int(b) for b in np.argsort(-np.asarray(scores), kind="stable")[:k]]


def global_match(ctx: RegistrationContext) -> None:
    """The classical global candidates: features matched at the data's resolution and a robust solver, from any
    initial rotation, each refined by the same ICP; cheapest first, and no more once one is confident. An answer
    resting on enough feature matches, which its ICP agreed with, is confident whatever its score
    (``core.confidence.certify``). Seeded (RANSAC); KISS-Matcher's answer varies a little with the order of its
    threads (docs/DESIGN.md, "Same request, same answer"). Its features see the surface from the input frame's origin
    (``PreparedClouds.viewpoint``)."""
    assert ctx.global_match is not None
    c = ctx.clouds
    for answer in ctx.global_match(c.src_unit, c.tgt_unit, c.resolution, ctx.seed, c.viewpoint):
        ctx.offer_or_defer(GLOBAL_MATCH, answer.transform, matches=answer.matches)
        ctx.offer_deferred()  # the waiting ones, best first (none without ``defer_doubtful``)
        if ctx.confident:
            return


def rescue(ctx: RegistrationContext) -> None:
    """Rescues of a still unconfident result (beyond the paper), cheapest first: the agent's coarse phase again from
    six starts 30° around the agent's best estimate (batched; the ``refine_top`` most promising are refined), on
    sparse clouds ICP from the best estimate shifted along each axis (``config.rescue_shifts``, until one is
    confident), a wide-window ICP from the input pose, on sparse clouds where the best is still far from confident
    (under ``config.rescue_global_starts`` times the status threshold) the agent's coarse phase from the global mode's
    well-spread starts, and last, on sparse clouds still under ``config.rescue_turns`` times the threshold, ICP from
    the best estimate turned by ``TURNS`` well-spread rotations, then by ``CENTRED_TURNS`` with the source centroid
    put on the target's (until one is confident). The restarts and the wide ICP both run: a wide ICP may be
    confidently wrong. The restarts centre on the agent's own estimate, not on a global match that scored higher: on
    sparse partial shapes that one is often far off, and the agent's is near enough for a 30° restart to reach the
    truth (ModelNet40 partial: docs/DESIGN.md). Not on dense clouds after the global match (``restarts_help``), which
    has searched every rotation there."""
    c, config = ctx.clouds, ctx.config
    batch: BatchScoreFn | None = None  # the target embedded once for both batched rescues

    def batched() -> BatchScoreFn:
        nonlocal batch
        if batch is None:
            with ctx.timer.stage("target_embedding"):
                batch = batch_score_fn(ctx.scorer, c.tgt_n)
                ctx.scorers.append(batch)
        return batch

    centre = ctx.best_agent or ctx.best
    if config.rescue_restarts and centre is not None and restarts_help(ctx):
        restarts = restart_transforms(centre.T_unit, c.src_n.mean(axis=0), local_rotations())
        offer_from_starts(ctx, batched(), restarts, RESTARTS, until_confident=False)
    if config.rescue_shifts and ctx.best is not None and not ctx.confident and not c.resolution.dense:
        offer_until_confident(ctx, SHIFTED_ICP, shifted_transforms(ctx.best.T_unit, config.rescue_shifts))
    if ctx.wide_icp is not None and not ctx.confident:
        with ctx.timer.stage("icp"):
            wide = ctx.wide_icp(c.src_unit, c.tgt_unit, np.eye(4), c.resolution)
        ctx.offer(WIDE_ICP, wide.transform)
    searched = config.init == "global"  # the global mode's own search began from those starts
    if far_from_confident(ctx, config.rescue_global_starts) and not c.resolution.dense and not searched:
        offer_from_starts(ctx, batched(), global_starts(ctx), GLOBAL_STARTS, until_confident=True)
    if far_from_confident(ctx, config.rescue_turns) and not c.resolution.dense:
        offer_until_confident(ctx, TURNED_ICP, turned_starts(ctx))


def offer_until_confident(ctx: RegistrationContext, name: str, estimates: Array) -> None:
    """Each of ``estimates: (B, 4, 4)`` refined and offered as ``name``, in order, until one is confident."""
    for T in estimates:
        ctx.offer(name, T)
        if ctx.confident:
            return


def turned_starts(ctx: RegistrationContext) -> Array:
    """The best estimate turned about where it puts the source by ``TURNS`` well-spread rotations, then by
    ``CENTRED_TURNS`` with the source centroid put on the target's: ``(TURNS + CENTRED_TURNS - 2, 4, 4)``."""
    assert ctx.best is not None
    c, T = ctx.clouds, ctx.best.T_unit
    centroid = c.src_unit.mean(axis=0)
    return np.concatenate(
        [
            turned_transforms(T, centroid, TURNS),
            centred_turned_transforms(T, centroid, c.tgt_unit.mean(axis=0), CENTRED_TURNS),
        ]
    )


def far_from_confident(ctx: RegistrationContext, fraction: float | None) -> bool:
    """Whether the best result so far scores under ``fraction`` of the status threshold (``None``: never)."""
    best = ctx.best
    return (
        fraction is not None
        and best is not None
        and not ctx.confident
        and (best.confidence.score < fraction * ctx.estimator.threshold)
    )


def offer_from_starts(
    ctx: RegistrationContext, score_fn: BatchScoreFn, starts: Array, name: str, until_confident: bool
) -> None:
    """The agent's coarse phase from ``starts`` (batched), its ``refine_top`` most promising runs offered as ``name``
    (best first; with ``until_confident``, none after a confident one)."""
    coarse = (ctx.schedule[0],) + (0,) * (len(ctx.schedule) - 1)
    more, scores = from_starts(ctx, score_fn, starts, coarse)
    first = len(ctx.agents)
    ctx.agents.extend(more)
    ctx.starts = np.concatenate([ctx.starts, starts])
    for k in _top(scores, ctx.config.refine_top):
        ctx.offer(name, more[k].transform, agent_index=first + k)
        if until_confident and ctx.confident:
            return


def restarts_help(ctx: RegistrationContext) -> bool:
    """Whether the restarts can add what the request has not tried: not on dense clouds once the global match has
    searched every rotation with features at the data's resolution. There, on 43 real-scan pairs, they never won a
    right answer and won wrong ones (on a LiDAR pair, where every candidate scores 0.12-0.16, one 18° off over the
    right ones), for 0.2-0.5 s each (docs/DESIGN.md, "Restarts on dense scans")."""
    return ctx.global_match is None or not ctx.clouds.resolution.dense


def polish(ctx: RegistrationContext) -> None:
    """The winner refined once more, each kind of data its finest way: ``polish_dense`` on dense clouds,
    ``finish_partial_overlap`` on sparse ones whose surface is not smooth at their resolution (ModelNet40's
    samples). Sparse smooth scans (a range scan cut to a few thousand points) keep the ICP stages' result: their
    point-to-plane stages end more precise than point-to-point can (the README's bunny pair, 4.7k points: 0.08°
    after the stages, 0.49° after the finish)."""
    resolution = ctx.clouds.resolution
    if resolution.dense:
        polish_dense(ctx)
    elif not resolution.smooth:
        finish_partial_overlap(ctx)


def polish_dense(ctx: RegistrationContext) -> None:
    """A ``converged`` winner refined once more (``PolishFn``), kept if it stays ``converged``: the polish is finer,
    not a new candidate, and it never decides the status. On a wrong pose GICP squeezes the overlap tighter: on the
    real-scan pairs it moved right answers' scores by at most 0.011 either way and raised wrong ones' by 0.04-0.05,
    one of them from 0.37 (``suspect``) to 0.42 (``converged``): docs/DESIGN.md, "The polish"."""
    assert ctx.best is not None
    c, best = ctx.clouds, ctx.best
    if ctx.polish is None or best.confidence.status != "converged":
        return
    T = ctx.polish(c.src_unit, c.tgt_unit, best.T_unit, c.resolution)
    if T is None:
        return
    confidence = ctx.judge(T, best.T_unit, best.confidence.matches)
    if confidence.status == "converged":
        ctx.best = replace(best, confidence=confidence, T_unit=T)


def finish_partial_overlap(ctx: RegistrationContext) -> None:
    """The winner on clouds that overlap in part (``confidence.overlap`` under ``PARTIAL_OVERLAP``), refined
    by symmetric robust point-to-point ICP (``core.robust_icp``) and kept, with the confidence it then has: the
    finish is more precise than Open3D's stages there (ModelNet40 partial, 150 pairs: 109 -> 118 right, and
    ``converged`` wrong answers 6 -> 2), and where the clouds overlap whole it gains nothing for its 6-10 ms
    (docs/DESIGN.md, "A finish for partial overlap")."""
    assert ctx.best is not None
    c, best = ctx.clouds, ctx.best
    if best.confidence.overlap >= PARTIAL_OVERLAP:
        return
    T = symmetric_robust_icp(c.src_index, c.tgt_index, best.T_unit, FINISH_KERNEL_SPACINGS * c.resolution.spacing)
    ctx.best = replace(best, confidence=ctx.judge(T, best.T_unit, best.confidence.matches), T_unit=T)


def register(
    source: npt.ArrayLike,
    target: npt.ArrayLike,
    scorer: Scorer,
    rng: np.random.Generator,
    config: RegistrationConfig = PAPER_V1,
    icp: IcpFn | None = None,
    rescue_icp: IcpFn | None = None,
    deadline: float | None = None,
    global_match_fn: GlobalMatchFn | None = None,
    seed: int = 0,
    polish_fn: PolishFn | None = None,
) -> Registration:
    """Register ``source: (N, 3)`` onto ``target: (M, 3)`` (any units) as ``config`` says; returns
    ``T_target_source`` (target ≈ R @ source + t) and the agent's own estimate, both in world units.

    ``icp``: the refinement (``None`` = PRANet-v1, whatever ``config.icp_stages`` say: the engine builds it from
    them); ``rescue_icp``: the wide ICP of the rescue; ``global_match_fn``: the classical global candidate
    (``None`` = off; it runs only when ``config.global_match``); ``seed``: the global match's; ``polish_fn``: the
    last refinement of a ``converged`` winner on dense clouds (runs only with ICP and ``config.polish``, which on
    sparse clouds finishes partial pairs with ``core.robust_icp`` instead). Raises
    ``DegenerateCloudError`` (a ``ValueError``) for unusable input and ``AgentTimeout`` past ``deadline``
    (``time.monotonic()`` seconds).
    """
    timer = StageTimer(STAGES)
    # 1. Prepare: validate, cap, unit frame, resolution, resample.
    with timer.stage("preprocess"):
        clouds = prepare(source, target, config.agent_points or scorer.n_points, rng)
        estimator = ConfidenceEstimator(clouds.src_index, clouds.tgt_index, clouds.resolution, config.threshold)
    ctx = RegistrationContext(
        clouds=clouds,
        config=config,
        scorer=scorer,
        schedule=tuple(config.schedule or scorer.schedule),
        rng=rng,
        seed=seed,
        timer=timer,
        estimator=estimator,
        icp=icp,
        wide_icp=rescue_icp if icp is not None else None,
        global_match=global_match_fn if icp is not None and config.global_match else None,
        polish=polish_fn if icp is not None and config.polish else None,
        deadline=deadline,
    )
    wide_search = config.init == "global"
    # 2. Embed the target once for this registration (tiled over the starts in global mode).
    with timer.stage("target_embedding"):
        score_fn = batch_score_fn(scorer, clouds.tgt_n) if wide_search else scorer.score_fn(clouds.tgt_n)
    ctx.scorers.append(score_fn)
    if wide_search:
        # 3. The wide search: the agent from every global start, and the global match beside it unless a start
        # is sure.
        agent_from_global_starts(ctx, score_fn)
        if ctx.global_match is not None and not ctx.sure:
            with timer.stage("global_match"):
                global_match(ctx)
    else:
        # 3. The agent from the input pose, to its first exit check (its coarse phase) when the global match may
        # follow; 4. the global match unless the agent is sure (``exit_confidence``), then the agent's estimate if
        # it waited behind it (``defer_doubtful``); 5. the rest of the agent's schedule, unless something is
        # confident by then.
        agent_from_input_pose(ctx, score_fn, until=global_match_after(ctx))
        if ctx.global_match is not None and not ctx.sure:
            with timer.stage("global_match"):
                global_match(ctx)
        if not ctx.confident:
            ctx.offer_deferred()
        if not ctx.confident:
            agent_from_input_pose(ctx, score_fn)
    # 6. The rescues of a still unconfident result.
    if icp is not None and not ctx.confident:
        with timer.stage("rescue"):
            rescue(ctx)
    # 7. The winner's polish.
    if icp is not None and config.polish:
        with timer.stage("polish"):
            polish(ctx)
    # 8. Back to world units.
    return to_world(ctx)


def to_world(ctx: RegistrationContext) -> Registration:
    """The best candidate, its agent run and the timings, in world units."""
    c, best = ctx.clouds, ctx.best
    assert best is not None
    norm = c.norm
    agent = ctx.agents[best.agent_index] if best.agent_index is not None else None
    shown = agent or ctx.agents[0]  # a classical winner shows the agent's own run from the input pose
    start = best.agent_index if best.agent_index is not None else 0
    T = norm.transform_to_world(best.T_unit)
    refined = best.refined
    timing = ctx.timer.report()
    return Registration(
        T_target_source=T,
        agent_T_target_source=norm.transform_to_world(shown.transform),
        trajectory=[(s.step, s.name, norm.transform_to_world(s.transform)) for s in shown.steps],
        icp=replace(refined, transform=T, inlier_rmse=refined.inlier_rmse / norm.scale) if refined else None,
        timing_ms=timing,
        agent=shown,
        normalization=norm,
        n_source=c.n_source,
        n_target=c.n_target,
        confidence=best.confidence,
        init=ctx.config.init,
        initial_transform=norm.transform_to_world(ctx.starts[start]),
        start_index=start,
        start_scores=ctx.start_scores,
        checks=ctx.checks,
        candidate=best.name,
        candidates=dict(ctx.tried),
        resolution=c.resolution.scaled(1.0 / norm.scale),
        n_used=(len(c.src_unit), len(c.tgt_unit)),
        network_calls=ctx.network_calls,
    )
