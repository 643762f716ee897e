"""Per-pair records and their summary; the pairs as every method sees them."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from pranet.core.metrics import SUCCESS_ROTATION_DEG, SUCCESS_TRANSLATION, isotropic_errors
from pranet.training.bench.methods import Outcome
from pranet.training.bench.tables import median, quantile
from pranet.training.samples import SETTINGS, Pair


@dataclass
class Record:
    setting: str
    pair: int
    method: str
    ms: float
    rotation_deg: float
    translation: float
    success: bool
    error: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    transform: list[list[float]] | None = None  # the estimate T_target_source


def score_pair(method: str, setting: str, i: int, pair: Pair, out: Outcome | None, error: str | None) -> Record:
    if out is None:
        return Record(setting, i, method, math.nan, math.nan, math.nan, False, error)
    rot, trans = isotropic_errors(out.transform, pair.T_gt)
    ok = bool(rot < SUCCESS_ROTATION_DEG and trans < SUCCESS_TRANSLATION)
    return Record(setting, i, method, out.ms, float(rot), float(trans), ok, None, out.extra, out.transform.tolist())


def summarize(records: Sequence[Record]) -> dict[str, Any]:
    ok = [r for r in records if r.error is None]
    return {
        "n": len(records),
        "errors": len(records) - len(ok),
        "ms_median": median([r.ms for r in ok]),
        "ms_p95": quantile([r.ms for r in ok], 0.95),
        "success": float(np.mean([r.success for r in records])) if records else math.nan,
        "rot_median": median([r.rotation_deg for r in ok]),
        "trans_median": median([r.translation for r in ok]),
        "steps_mean": float(np.mean(steps))
        if (steps := [r.extra["n_steps"] for r in ok if "n_steps" in r.extra])
        else math.nan,
    }


def as_float32(pair: Pair) -> Pair:
    """The pair with both clouds rounded to float32, as the HTTP client sends them: every method, in-process or
    over HTTP, then registers exactly the same numbers."""
    return replace(
        pair,
        source=pair.source.astype(np.float32).astype(np.float64),
        target=pair.target.astype(np.float32).astype(np.float64),
    )


def pair_seed(seed: int, setting: str, i: int) -> int:
    """One integer seed per pair, shared by every method (the service takes it as ``seed``): PRANet in-process
    and over HTTP resample the same points."""
    return int(np.random.default_rng([seed, SETTINGS.index(setting), i, 99]).integers(0, 2**31 - 1))
