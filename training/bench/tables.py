"""Statistics and markdown tables of the report."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np


def quantile(x: Sequence[float], q: float) -> float:
    a = np.asarray([v for v in x if v is not None and math.isfinite(v)], dtype=np.float64)
    return float(np.quantile(a, q)) if len(a) else math.nan


def median(x: Sequence[float]) -> float:
    return quantile(x, 0.5)


def fmt(x: float | None, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    if abs(x) >= 100:
        return f"{x:.0f}"
    return f"{x:.{digits}g}"


def md_table(head: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A markdown pipe table (readable as plain text too)."""
    cells = [[str(c) for c in head]] + [[c if isinstance(c, str) else fmt(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(head))]
    line = lambda r: "| " + " | ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) + " |"  # noqa: E731
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([line(cells[0]), sep, *(line(r) for r in cells[1:])])


def stats(samples: Sequence[float]) -> dict[str, float]:
    return {"median": median(samples), "p95": quantile(samples, 0.95), "n": len(samples)}
