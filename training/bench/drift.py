"""int8 against fp32: reward drift along the fp32 agent's trajectories."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from pranet.core.se3 import Array


class DriftScorer:
    """A scorer running the fp32 model (whose rewards drive the agent) and the int8 one on the same states."""

    def __init__(self, fp32: Any, int8: Any):
        self.fp32, self.int8 = fp32, int8
        self.table, self.schedule, self.n_points = fp32.table, fp32.schedule, fp32.n_points
        self.pairs: list[tuple[np.ndarray, np.ndarray]] = []

    def score_fn(self, target: Any) -> Callable[[Array, Array], np.ndarray]:
        f32, f8 = self.fp32.score_fn(target), self.int8.score_fn(target)

        def score(source: Array, tgt: Array) -> np.ndarray:
            r32 = np.asarray(f32(source, tgt), dtype=np.float64)
            self.pairs.append((r32, np.asarray(f8(source, tgt), dtype=np.float64)))
            return r32

        return score


def drift_summary(pairs: Sequence[tuple[np.ndarray, np.ndarray]], table: Any, schedule: Sequence[int]) -> dict:
    """Per step: |Δ| over all actions, and whether both precisions pick the same action of the step's scale."""
    if not pairs:
        return {}
    diffs = np.array([np.abs(a - b) for a, b in pairs])
    bounds = np.cumsum(schedule)
    n_per_reg = int(bounds[-1])
    agree = []
    for j, (a, b) in enumerate(pairs):
        scale = int(np.searchsorted(bounds, j % n_per_reg, side="right"))
        idx = table.indices_of_scale(min(scale, len(schedule) - 1))
        agree.append(np.argmax(a[idx]) == np.argmax(b[idx]))
    scale_of_rewards = float(np.mean([np.abs(a).mean() for a, _ in pairs]))
    return {
        "states": len(pairs),
        "max_abs": float(diffs.max()),
        "mean_abs": float(diffs.mean()),
        "p99_abs": float(np.quantile(diffs, 0.99)),
        "mean_abs_reward_fp32": scale_of_rewards,
        "argmax_agreement": float(np.mean(agree)),
    }
