"""Per-step latency of onnxruntime session options and of the int8 graphs, measured interleaved."""

from __future__ import annotations

import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from pranet.core.se3 import Array
from pranet.training.bench.tables import median, quantile

ORT_VARIANTS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("default (all, 2 threads, sequential, arena, mem pattern, no spinning)", {}),
    ("optimization=none", {"optimization": "none"}),
    ("optimization=basic", {"optimization": "basic"}),
    ("optimization=extended", {"optimization": "extended"}),
    ("threads=1", {"threads": 1}),
    ("spinning on (onnxruntime's default)", {"spinning": True}),
    ("memory arena off", {"arena": False}),
    ("memory pattern off", {"mem_pattern": False}),
    ("execution=parallel (2 inter-op threads)", {"execution": "parallel"}),
    ("int8", {"precision": "int8"}),
    ("int8, threads=1", {"precision": "int8", "threads": 1}),
)


def ort_variants_table(
    model_dir: str | None,
    int8_dir: Path | None,
    threads: int,
    source: Array,
    target: Array,
    calls: int,
    per_round: int = 10,
) -> list[dict[str, Any]]:
    """ms per score call (= per agent step, minus the agent's own bookkeeping) and per target embedding, for
    each variant, ``calls`` calls in all: in rounds of ``per_round`` calls per variant, the variants' order
    rotated per round. Only one variant's sessions exist at a time (opened for its turn, then closed), as in a
    service worker: idle thread pools of other sessions, spinning, would otherwise slow whichever runs next."""
    import gc

    from pranet.engine.runtime import RewardModel

    variants = []
    for label, kw in ORT_VARIANTS:
        kw = {"threads": threads, **kw}
        if kw.get("precision") == "int8":
            if int8_dir is None:
                continue
            variants.append((label, kw, int8_dir))
        else:
            variants.append((label, kw, model_dir))
    samples: dict[str, list[float]] = {label: [] for label, _, _ in variants}
    round_best: dict[str, list[float]] = {label: [] for label, _, _ in variants}
    round_median: dict[str, list[float]] = {label: [] for label, _, _ in variants}
    embed: dict[str, list[float]] = {label: [] for label, _, _ in variants}
    graph_calls: dict[str, Counter] = {label: Counter(full=0, head=0) for label, _, _ in variants}
    per_round = max(1, min(per_round, calls))
    rounds = max(1, calls // per_round)
    for r in range(rounds):
        k = r % len(variants)
        for label, kw, where in variants[k:] + variants[:k]:  # rotated: no variant always runs first
            # The same source every call: with head reuse the runtime would re-score it with head.onnx alone
            # (it has not moved), and this table would time the MLP heads instead of score.onnx.
            model = RewardModel.load(where, reuse_translations=False, **kw)
            f = model.score_fn(target)
            f(source, target)  # first call: kNN graph, allocations
            this_round = []
            for _ in range(per_round):
                t0 = time.perf_counter()
                f(source, target)
                this_round.append((time.perf_counter() - t0) * 1e3)
            for graph, n in f.calls.items():
                graph_calls[label][graph] += n
            samples[label] += this_round
            round_best[label].append(min(this_round))
            round_median[label].append(float(np.median(this_round)))
            t0 = time.perf_counter()
            model.embed(target)
            embed[label].append((time.perf_counter() - t0) * 1e3)
            del f, model
            gc.collect()  # close the sessions (and their thread pools) before the next variant
    default = variants[0][0]
    return [
        {
            "variant": label,
            "options": kw,
            "score_ms": median(samples[label]),
            "score_min_ms": min(samples[label]),
            "score_p90_ms": quantile(samples[label], 0.9),
            "embed_ms": median(embed[label]),
            # Paired: per round, this variant's best (median) call over the default's in the same round.
            "vs_default": median([a / b for a, b in zip(round_best[label], round_best[default], strict=True)]),
            "vs_default_busy": median([a / b for a, b in zip(round_median[label], round_median[default], strict=True)]),
            "calls": len(samples[label]),
            "graph_calls": dict(graph_calls[label]),  # score.onnx ("full") and head.onnx runs: head must stay 0
        }
        for label, kw, _ in variants
    ]
