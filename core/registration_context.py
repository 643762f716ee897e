"""The state of one registration, on one object that every stage reads: the prepared clouds, the config, the
injected functions (reward model, ICP, global match), the timer, and the candidates so far.

``prepare`` turns the two input clouds into ``PreparedClouds``: checked, capped at ``MAX_WORKING_POINTS`` (a
fixed-seed subset: memory and time stay bounded for million-point scans), mapped into the model's unit frame,
measured (``core.resolution``) and sampled to the agent's N points: a smaller cloud is used whole, each point once
(``agent_sample``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from pranet.core.actions import ActionTable
from pranet.core.agent import AgentResult, ScoreFn
from pranet.core.confidence import CERTIFYING_MATCHES, Confidence, ConfidenceEstimator, certify
from pranet.core.nearest import PointIndex, subsample
from pranet.core.preprocess import Normalization, check_cloud, fit_normalization, resample
from pranet.core.registration_config import MIN_AGENT_POINTS, RegistrationConfig
from pranet.core.registration_types import Candidate, Deferred, GlobalMatchFn, IcpFn, IcpResult, PolishFn
from pranet.core.resolution import Resolution, measure_resolution
from pranet.core.se3 import Array, apply_transform, rotation_angle
from pranet.core.stage_timer import StageTimer

# Larger clouds are cut to this many points (fixed seed) before anything else: a 1M-point LiDAR scan then costs
# what a 200k-point one does, and the working copies stay under ~20 MB (docs/DESIGN.md, "Large clouds").
MAX_WORKING_POINTS = 200_000
RANK_QUERIES = 256  # query points per direction of the quick confidence that ranks agent starts


class Scorer(Protocol):
    """What the pipeline needs of a reward model (``pranet.engine.runtime.RewardModel`` is one)."""

    table: ActionTable
    schedule: tuple[int, ...]
    n_points: int

    def score_fn(self, target: npt.ArrayLike) -> ScoreFn: ...


@dataclass(frozen=True)
class PreparedClouds:
    """Both clouds of one registration, ready for every stage."""

    n_source: int  # points as given
    n_target: int
    norm: Normalization  # world -> unit frame
    src_unit: Array  # (Ns', 3) the working source (capped), unit frame
    tgt_unit: Array  # (Nt', 3)
    src_index: PointIndex  # of src_unit: built once, shared by the resolution and the confidence
    tgt_index: PointIndex
    resolution: Resolution  # unit frame
    src_n: Array  # (N, 3) resampled for the agent
    tgt_n: Array  # (N, 3)

    @property
    def viewpoint(self) -> Array:
        """The input frame's origin in the unit frame, (3,): where a scan's sensor was (scans come in their sensor's
        frame), for the global match's normals."""
        return self.norm.to_unit(np.zeros((1, 3)))[0]


def agent_sample(points: Array, n_points: int, rng: np.random.Generator) -> Array:
    """``n_points`` distinct rows of ``points`` in random order, or all of them when there are fewer, but never fewer
    than ``MIN_AGENT_POINTS`` (the network's k-nearest-neighbour graph needs that many).

    A repeated point adds nothing to the matching and weighs its soft assignment toward itself, so a cloud smaller
    than the agent's N is not padded with repeats (docs/DESIGN.md, "Every point for the paper's agent").
    """
    return resample(points, min(n_points, max(len(points), MIN_AGENT_POINTS)), rng)


def prepare(
    source: npt.ArrayLike,
    target: npt.ArrayLike,
    n_points: int,
    rng: np.random.Generator,
    max_points: int = MAX_WORKING_POINTS,
) -> PreparedClouds:
    """Validate, cap, normalise to the unit frame (one similarity for both clouds), measure, resample."""
    src = check_cloud(source, "source")
    tgt = check_cloud(target, "target")
    src_work, tgt_work = subsample(src, max_points, seed=11), subsample(tgt, max_points, seed=12)
    norm = fit_normalization(src_work, tgt_work)
    src_unit, tgt_unit = norm.to_unit(src_work), norm.to_unit(tgt_work)
    src_index, tgt_index = PointIndex(src_unit), PointIndex(tgt_unit)
    return PreparedClouds(
        n_source=len(src),
        n_target=len(tgt),
        norm=norm,
        src_unit=src_unit,
        tgt_unit=tgt_unit,
        src_index=src_index,
        tgt_index=tgt_index,
        resolution=measure_resolution(src_index, tgt_index),
        src_n=agent_sample(src_unit, n_points, rng),
        tgt_n=agent_sample(tgt_unit, n_points, rng),
    )


def estimate_key(T_unit: npt.ArrayLike) -> bytes:
    """An estimate's identity (its exact float64 bytes): what ``offer`` has seen before."""
    return np.ascontiguousarray(T_unit, dtype=np.float64).tobytes()


@dataclass
class RegistrationContext:
    """One registration in progress. Stages read the clouds and functions and ``offer`` their candidates;
    the most confident one so far is ``best``."""

    clouds: PreparedClouds
    config: RegistrationConfig
    scorer: Scorer
    schedule: tuple[int, ...]
    rng: np.random.Generator
    seed: int  # of the global match (a pure function of the request)
    timer: StageTimer
    estimator: ConfidenceEstimator
    icp: IcpFn | None = None  # the refinement at the data's resolution (None: PRANet-v1)
    wide_icp: IcpFn | None = None  # the wide-window ICP of the rescue
    global_match: GlobalMatchFn | None = None
    polish: PolishFn | None = None
    deadline: float | None = None
    # Filled in by the stages:
    starts: Array = field(default_factory=lambda: np.eye(4)[None])  # (B, 4, 4) every agent run's start, unit frame
    agents: list[AgentResult] = field(default_factory=list)  # every agent run, in the order of ``starts``
    agent_scheduled: int = 0  # scheduled steps the input-pose run has done (early stops may take fewer)
    checks: list[tuple[int, float]] = field(default_factory=list)  # exit checks: (agent steps, confidence)
    start_scores: list[float] = field(default_factory=list)  # global mode: each start's quick confidence
    best: Candidate | None = None
    best_agent: Candidate | None = None  # the most confident of the agent's own candidates (its runs, refined)
    tried: dict[str, float] = field(default_factory=dict)  # candidate name -> its best confidence
    deferred: list[Deferred] = field(default_factory=list)  # doubtful candidates waiting, part-refined
    offered: dict[bytes, Candidate] = field(default_factory=dict)  # estimate (its bytes) -> what it became
    scorers: list[object] = field(default_factory=list)  # the score functions made (their ``calls``, when counted)

    @property
    def network_calls(self) -> int:
        """Network evaluations so far, from the score functions that count them (``RewardModel``'s do): the full calls
        of both phases and the fine phase's match-only ones (its Sinkhorn rounds, most of a fine call's cost); not the
        head-only re-scorings (microseconds)."""
        calls = [getattr(fn, "calls", {}) for fn in self.scorers]
        return sum(int(c.get(graph, 0)) for c in calls for graph in ("full", "fine", "match"))

    def loop(self, score_fn: object) -> dict:
        """The agent loop's keyword arguments when it scores with ``score_fn`` (its ``pose``, when the model has
        one, is what the walk asks; its ``fine``, the fine phase's scorer where ``config.uses_fine_call``)."""
        c = self.config
        pose_fn = getattr(score_fn, "pose", None)
        available = getattr(score_fn, "fine", None)
        use_fine = c.uses_fine_call(available is not None)
        if use_fine and available is None:
            raise ValueError(
                "fine_matching: this model has no fine-phase call (score_fine.onnx); "
                "re-export its checkpoint with pranet-export"
            )
        return {
            "policy": c.policy,
            "rng": self.rng,
            "early_stop": c.early_stop,
            "deadline": self.deadline,
            "pose_fn": pose_fn,
            "walk_steps": c.walk_steps,
            "confirm_arrival": c.confirm_arrival or not c.refines,
            "fine_score_fn": available if use_fine else None,
        }

    @property
    def confident(self) -> bool:
        return self.best is not None and self.best.confidence.status == "converged"

    @property
    def sure(self) -> bool:
        """Confident enough to skip the global match: ``converged`` and at least ``config.exit_confidence``."""
        bar = self.config.exit_confidence
        return self.confident and (bar is None or self.best.confidence.score >= bar)  # type: ignore[union-attr]

    def evaluate(self, T_unit: Array) -> Confidence:
        with self.timer.stage("confidence"):
            return self.estimator.evaluate(T_unit)

    def refine(self, T_unit: Array, bar: float | None) -> tuple[IcpResult, float | None]:
        """ICP from ``T_unit``. With ``bar``, the quick confidence after the gate's first iterations is asked: under
        ``bar`` times the status threshold, the estimate is not refined further. Returns the result and that quick
        confidence (``None``: not asked)."""
        assert self.icp is not None
        c, quick = self.clouds, []

        def proceed(T: Array) -> bool:
            with self.timer.stage("confidence"):
                quick.append(self.estimator.evaluate(T, RANK_QUERIES).score)
            return quick[-1] >= bar * self.estimator.threshold  # type: ignore[operator]

        with self.timer.stage("icp"):
            if bar is None:
                return self.icp(c.src_unit, c.tgt_unit, T_unit, c.resolution), None
            result = self.icp(c.src_unit, c.tgt_unit, T_unit, c.resolution, proceed=proceed)
        return result, (quick[-1] if quick else None)

    def judge(self, T_unit: Array, estimate: Array | None = None, matches: int = 0) -> Confidence:
        """The confidence of ``T_unit``; for a global answer resting on ``matches`` feature matches, refined from
        ``estimate``, certified by them where they suffice (``core.confidence.certify``)."""
        confidence = self.evaluate(T_unit)
        if matches < CERTIFYING_MATCHES or estimate is None:
            return confidence
        centroid = self.estimator.source_queries.mean(axis=0, keepdims=True)
        shift = float(np.linalg.norm(apply_transform(T_unit, centroid) - apply_transform(estimate, centroid)))
        turn = float(np.degrees(rotation_angle(np.asarray(T_unit)[:3, :3] @ np.asarray(estimate)[:3, :3].T)))
        resolution = self.clouds.resolution
        return certify(confidence, matches, shift / resolution.voxel, turn, resolution.dense)

    def offer(
        self,
        name: str,
        T_unit: Array,
        agent_index: int | None = None,
        refined: IcpResult | None = None,
        matches: int = 0,
    ) -> Candidate:
        """Refine ``T_unit`` (when ICP is on, and unless ``refined`` already is its refinement), score it, and keep
        it if it beats ``best``. With ``icp_guard``, a refinement that scores below the estimate it started from is
        dropped: point-to-plane ICP on a sparse partial shape can slide along a flat part, or solve a degenerate
        system, and end far off (docs/DESIGN.md, "When ICP makes it worse"). ``matches``: a global answer's feature
        matches, which may certify it (``judge``).

        An estimate offered before is not refined and scored again: an agent that stopped early reaches its next
        exit check where it stood at the last one (on an RGB-D fragment that was 350 ms of ICP spent twice)."""
        key = estimate_key(T_unit)
        if refined is None and key in self.offered:
            seen = self.offered[key]
            self.tried[name] = max(self.tried.get(name, 0.0), seen.confidence.score)
            return seen
        if refined is None and self.icp is not None:
            refined, _ = self.refine(T_unit, self.config.icp_gate)
        T = refined.transform if refined is not None else T_unit
        confidence = self.judge(T, T_unit, matches)
        if refined is not None and self.config.icp_guard:
            unrefined = self.evaluate(T_unit)  # the matches certify the answer ICP agreed with, not the raw one
            if unrefined.outranks(confidence):
                T, refined, confidence = T_unit, None, unrefined
        candidate = Candidate(confidence, name, T, refined, agent_index)
        self.tried[name] = max(self.tried.get(name, 0.0), candidate.confidence.score)
        if candidate.beats(self.best):
            self.best = candidate
        if agent_index is not None and candidate.beats(self.best_agent):
            self.best_agent = candidate
        self.offered[key] = candidate
        return candidate

    def offer_or_defer(
        self, name: str, T_unit: Array, agent_index: int | None = None, steps: int | None = None, matches: int = 0
    ) -> Candidate | None:
        """``offer``, unless the estimate's quick confidence after the ICP gate's iterations is between the gate
        and the status threshold: then the rest of its ICP waits in ``deferred`` for ``offer_deferred`` and
        ``None`` is returned (only with ``defer_doubtful``). Such an estimate is as often wrong as right, and a
        wrong one takes every iteration of every ICP stage (100-250 ms on an object scan); waiting, it is refined
        only if a more promising candidate does not settle the request first (docs/DESIGN.md, "Doubtful candidates
        wait their turn"). Dense clouds only: on sparse ones (ModelNet40's) a wrong estimate's whole ICP costs a
        few milliseconds, less than the global match that waiting makes it run."""
        gate = self.config.icp_gate
        key = estimate_key(T_unit)
        if key in self.offered:
            return self.offered[key]
        if any(estimate_key(d.T_unit) == key for d in self.deferred):
            return None  # already waiting
        if not self.config.defer_doubtful or self.icp is None or gate is None or not self.clouds.resolution.dense:
            return self.offer(name, T_unit, agent_index, matches=matches)
        refined, quick = self.refine(T_unit, 1.0)
        if quick is not None and gate * self.estimator.threshold <= quick < self.estimator.threshold:
            self.deferred.append(Deferred(name, T_unit, refined.transform, quick, agent_index, steps, matches))
            return None
        # promising, or hopeless as the gate left it
        return self.offer(name, T_unit, agent_index, refined=refined, matches=matches)

    def offer_deferred(self) -> None:
        """The waiting candidates, the best quick confidence first, each refined from where the gate left it (as a
        promising one would have gone on) and offered, until one is ``sure``; an agent's exit check is recorded
        with its confidence. Those left unrefined are dropped."""
        waiting = sorted(self.deferred, key=lambda d: -d.quick)
        self.deferred.clear()
        for d in waiting:
            if self.sure:
                return
            refined, _ = self.refine(d.part_refined, None)
            checked = self.offer(d.name, d.T_unit, d.agent_index, refined=refined, matches=d.matches)
            if d.steps is not None:
                self.checks.append((d.steps, checked.confidence.score))

    def quick_scores(self, agents: Sequence[AgentResult]) -> list[float]:
        """A quick confidence of each agent's result (fewer query points): to rank starts before refining them."""
        with self.timer.stage("confidence"):
            return [self.estimator.evaluate(a.transform, RANK_QUERIES).score for a in agents]
