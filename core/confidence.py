"""How far to trust a registration result, from the data alone, at the data's own resolution.

Partial scans overlap only in part, so the fraction of the source that lands on the target says how much they
overlap, not whether the result is right. What does say it is how *tight* the overlap is: after a right
registration, the points that come near the other cloud lie on it, within about one sampling spacing; after a
wrong one, surfaces cross or graze and the points near the other cloud spread over several spacings. So, in the
unit frame, with ``spacing`` the data's resolution (``core.resolution``) and fixed-seed query subsets of both
clouds (at most ``max_queries`` each) against indexes (KD-trees) of the whole working clouds:

- ``inlier_ratio``: the fraction of source points within ``tau = INLIER_SPACINGS * spacing`` of the target;
- ``overlap``: the fraction within ``OVERLAP_SPACINGS * spacing``: the source's part in the overlap region;
- ``precision_source = inlier_ratio / overlap``, and ``precision_target`` the same from the target's side (its
  points moved back by the inverse transform, against the source's tree): how tight the overlap region is;
- ``score`` (the response's ``confidence``, in [0, 1]) = the smaller precision, times a factor that falls to 0
  as the overlap shrinks below ``MIN_OVERLAP`` (a handful of points touching by chance is no evidence).

``status`` is ``"converged"`` at ``score >= threshold``, else ``"suspect"``. The multiples and the threshold were
chosen on real scan pairs and ModelNet40 partial pairs (right and wrong results of the pipeline and of ICP from
random poses): docs/DESIGN.md, "A confidence for partial scans"; ``scripts/confidence_eval.py`` measures it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np
import numpy.typing as npt

from pranet.core.nearest import PointIndex, subsample
from pranet.core.resolution import SPARSE_FROM, Resolution
from pranet.core.se3 import apply_transform, inverse

# The status threshold; the same threshold ends the request at an exit check and decides whether the global match
# and the rescues run, so it leans towards recall: a missed failure is not rescued, a false alarm costs time.
DEFAULT_THRESHOLD = 0.40
# Sparse clouds (few points over the object, so one spacing is a sizeable part of it) need a higher bar: there an
# ICP-converged wrong pose looks tight by chance. The threshold rises linearly from DEFAULT_THRESHOLD at a relative
# spacing (spacing / the clouds' radius) of SPARSE_FROM to SPARSE_THRESHOLD at SPARSE_AT. Measured: the real scans
# have 0.0002-0.0074, ModelNet40's 1024-point shapes 0.025-0.076; on ModelNet40 noisy pairs right results score
# 0.69-0.77 and the agent's wrong ones 0.46-0.57 (docs/DESIGN.md, "A confidence for partial scans").
SPARSE_AT, SPARSE_THRESHOLD = 0.025, 0.62
INLIER_SPACINGS = 1.0  # tau: one spacing
OVERLAP_SPACINGS = 4.0  # the overlap region: points within one voxel of the other cloud
MIN_OVERLAP = 0.1  # below this overlap (of the smaller side) the score falls linearly to 0
MAX_QUERIES = 2048  # query points per direction: 2-4 ms per evaluation, whatever the clouds' size
# A second way to be sure, for what the tightness cannot judge: a global match resting on this many mutually
# consistent feature matches (KISS-Matcher's final inliers), which its ICP refinement kept within CERTIFIED_SHIFT
# voxels (the source's centroid) and CERTIFIED_TURN_DEG, is ``converged`` whatever its score. On ring LiDAR every
# answer scores 0.1-0.2 (the rings of two scans align when the sensors stand at the same place, so a slid answer
# is as tight as the right one) while the right global match rests on 80-260 matches; over 58 real-scan runs, right
# answers rested on 8-650 matches and wrong ones on at most 7 (docs/DESIGN.md, "Matches as a certificate"). Dense
# clouds only: on ModelNet40's sparse samples it was never measured.
CERTIFYING_MATCHES = 25
CERTIFIED_SHIFT_VOXELS = 2.0
CERTIFIED_TURN_DEG = 5.0


@dataclass(frozen=True)
class Confidence:
    score: float  # in [0, 1]: min(precision_source, precision_target), scaled down for tiny overlaps
    status: str  # "converged" | "suspect"
    inlier_ratio: float  # source points within tau of the target
    overlap: float  # source points within the overlap distance of the target
    precision_source: float  # inlier_ratio / overlap
    precision_target: float  # the same, from the target's side
    tau: float  # inlier distance, unit frame
    spacing: float  # the data's spacing, unit frame
    matches: int = 0  # the feature matches that certify it (``certify``); 0: judged by its score alone

    def outranks(self, other: Confidence) -> bool:
        """Whether a result of this confidence ranks above one of ``other``: ``converged`` above ``suspect``, then
        certified by feature matches (``certify``) above judged by its score alone, then the higher score. A
        certificate outranks a higher score because on a scene the score can be fooled: an agent answer slid 0.47 m
        along a 3DMatch kitchen's cabinets scored 0.56 against the certified right answer's 0.51 (docs/DESIGN.md,
        "A certificate outranks a score"); no wrong answer has yet rested on more than 7 matches."""
        return self._rank() > other._rank()

    def _rank(self) -> tuple[bool, bool, float]:
        return self.status == "converged", self.matches > 0, self.score

    def as_dict(self) -> dict[str, float | str]:
        return asdict(self)


def status_threshold(base: float, relative_spacing: float) -> float:
    """The threshold of ``status`` for clouds whose spacing is ``relative_spacing`` of their radius: ``base`` for
    dense clouds, rising to ``SPARSE_THRESHOLD`` (never below ``base``) for sparse ones."""
    x = float(np.clip((relative_spacing - SPARSE_FROM) / (SPARSE_AT - SPARSE_FROM), 0.0, 1.0))
    return max(base, base + x * (SPARSE_THRESHOLD - base))


def certify(confidence: Confidence, matches: int, shift_voxels: float, turn_deg: float, dense: bool) -> Confidence:
    """``confidence`` of a global answer resting on ``matches`` feature matches, which its refinement moved by
    ``shift_voxels`` (the source's centroid, in voxels) and ``turn_deg``: ``converged`` when the matches certify it
    (``CERTIFYING_MATCHES``, on ``dense`` clouds), else as its score says."""
    sure = (
        dense
        and matches >= CERTIFYING_MATCHES
        and shift_voxels <= CERTIFIED_SHIFT_VOXELS
        and turn_deg <= CERTIFIED_TURN_DEG
    )
    if not sure:
        return confidence
    return replace(confidence, status="converged", matches=matches)


class ConfidenceEstimator:
    """Both clouds prepared once (their KD-trees and query subsets); ``evaluate`` then scores any number of
    ``T_target_source`` candidates (the pipeline ranks every candidate this way)."""

    def __init__(
        self,
        source: npt.ArrayLike | PointIndex,
        target: npt.ArrayLike | PointIndex,
        resolution: Resolution,
        threshold: float = DEFAULT_THRESHOLD,
        max_queries: int = MAX_QUERIES,
    ):
        """``source: (N, 3)``, ``target: (M, 3)`` in one frame, or their indexes (built once per registration);
        ``resolution``: theirs (``measure_resolution``), whose relative spacing sets the status threshold."""
        self.source_index = source if isinstance(source, PointIndex) else PointIndex(source)
        self.target_index = target if isinstance(target, PointIndex) else PointIndex(target)
        self.source_queries = subsample(self.source_index.points, max_queries, seed=2)  # (<= Q, 3)
        self.target_queries = subsample(self.target_index.points, max_queries, seed=3)
        self.spacing = resolution.spacing
        self.tau = INLIER_SPACINGS * resolution.spacing
        self.near = OVERLAP_SPACINGS * resolution.spacing
        self.threshold = status_threshold(threshold, resolution.relative_spacing)

    def evaluate(self, T_target_source: npt.ArrayLike, n_queries: int | None = None) -> Confidence:
        """The confidence of ``T_target_source: (4, 4)`` (unit frame). ``n_queries``: fewer query points per
        direction (a quick ranking of many candidates)."""
        T = np.asarray(T_target_source, dtype=np.float64)
        q_src, q_tgt = self.source_queries[:n_queries], self.target_queries[:n_queries]
        # Searched only up to the overlap radius: unbounded searches for the far points of a wrong pose cost 40 ms
        # per evaluation on a 40k-point scan, not 2.
        bound = self.near * (1.0 + 1e-9)
        d_source = self.target_index.nearest(apply_transform(T, q_src), bound)  # (Q,)
        d_target = self.source_index.nearest(apply_transform(inverse(T), q_tgt), bound)  # (Q,)
        inliers_s, overlap_s = float(np.mean(d_source <= self.tau)), float(np.mean(d_source <= self.near))
        inliers_t, overlap_t = float(np.mean(d_target <= self.tau)), float(np.mean(d_target <= self.near))
        precision_s = inliers_s / overlap_s if overlap_s > 0 else 0.0
        precision_t = inliers_t / overlap_t if overlap_t > 0 else 0.0
        support = min(1.0, min(overlap_s, overlap_t) / MIN_OVERLAP)
        score = min(precision_s, precision_t) * support
        return Confidence(
            score=score,
            status="converged" if score >= self.threshold else "suspect",
            inlier_ratio=inliers_s,
            overlap=overlap_s,
            precision_source=precision_s,
            precision_target=precision_t,
            tau=self.tau,
            spacing=self.spacing,
        )


def estimate_confidence(
    source: npt.ArrayLike,
    target: npt.ArrayLike,
    T_target_source: npt.ArrayLike,
    threshold: float = DEFAULT_THRESHOLD,
    resolution: Resolution | None = None,
) -> Confidence:
    """The confidence of ``T_target_source`` for ``source: (N, 3)`` onto ``target: (M, 3)`` (any one frame);
    ``resolution``: the data's (default: measured on the two clouds)."""
    from pranet.core.resolution import measure_resolution

    src, tgt = PointIndex(source), PointIndex(target)
    resolution = resolution or measure_resolution(src, tgt)
    return ConfidenceEstimator(src, tgt, resolution, threshold).evaluate(T_target_source)
