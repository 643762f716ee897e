"""The methods: each maps (pair, pair seed) to (T_target_source, latency ms, extra)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pranet.core.se3 import Array
from pranet.training.bench.catalog import SMALL_GICP_DOWNSAMPLING
from pranet.training.samples import Pair


@dataclass
class Outcome:
    transform: Array
    ms: float
    extra: dict[str, Any] = field(default_factory=dict)


MethodFn = Callable[[Pair, int], Outcome]


def small_gicp_align(
    source: Array, target: Array, max_distance: float = 0.5, threads: int = 1, max_iterations: int = 100
) -> Array:
    """GICP from the identity with small_gicp (covariances from 20 neighbours after a fine voxel grid)."""
    import small_gicp

    r = small_gicp.align(
        np.ascontiguousarray(target, dtype=np.float64),
        np.ascontiguousarray(source, dtype=np.float64),
        registration_type="GICP",
        downsampling_resolution=SMALL_GICP_DOWNSAMPLING,
        max_correspondence_distance=max_distance,
        num_threads=threads,
        max_iterations=max_iterations,
    )
    return np.asarray(r.T_target_source, dtype=np.float64).copy()


def pranet_method(engine: Any, config: Any) -> MethodFn:
    """PRANet in-process through ``engine`` (``pranet.engine.Engine``) as ``config`` (a ``RegistrationConfig``)."""

    def run(pair: Pair, seed: int) -> Outcome:
        t0 = time.perf_counter()
        # The global match seeded with the request's seed, as the service seeds it.
        reg = engine.register(pair.source, pair.target, config, np.random.default_rng(seed), seed=seed)
        ms = (time.perf_counter() - t0) * 1e3
        extra = {
            "timing_ms": reg.timing_ms,
            "n_steps": len(reg.trajectory),
            "agent_transform": reg.agent_T_target_source,
            "status": reg.confidence.status if reg.confidence is not None else None,
            "confidence": reg.confidence.score if reg.confidence is not None else None,
            "candidate": reg.candidate,
            "network_calls": reg.network_calls,
        }
        if reg.agent is not None:
            extra.update(steps_by_graph(reg.agent.steps, engine.scorer, config))
        return Outcome(reg.T_target_source, ms, extra)

    return run


def steps_by_graph(steps: Sequence[Any], scorer: Any, config: Any) -> dict[str, int]:
    """Which graph scored the agent's ``steps``: ``fine_steps`` through the fine phase's call (``score_fine.onnx``,
    where ``config.uses_fine_call``), ``match_steps`` the fine steps that follow a fine-phase translation (re-scored
    by ``match_fine.onnx`` where the runtime has it), ``after_translation`` the other steps that follow a translation
    (re-scored by ``head.onnx`` when the runtime reuses), the rest ``score.onnx``."""
    table = scorer.table
    fine = config.uses_fine_call(bool(getattr(scorer, "has_fine_call", False)))
    match = fine and bool(getattr(scorer, "has_match_call", False))
    moved = set(np.asarray(table.translation_indices).tolist())
    by_fine = [fine and table.actions[s.action].scale > 0 for s in steps]
    pairs = list(zip(steps[:-1], by_fine[:-1], by_fine[1:], strict=True))
    after = [prev.action in moved and not f for prev, _, f in pairs]
    by_match = [match and prev.action in moved and f_prev and f for prev, f_prev, f in pairs]
    return {"after_translation": sum(after), "fine_steps": sum(by_fine) - sum(by_match), "match_steps": sum(by_match)}


def refined_by(coarse: Callable[[Array, Array, np.random.Generator], Array], icp: Any):
    """``coarse`` (a baseline without refinement) followed by PRANet's ICP (an ``IcpFn``, unit frame, at the data's
    measured resolution), as the pipeline runs it: the classical peer with the same refinement as the service."""
    from pranet.core.preprocess import fit_normalization
    from pranet.core.resolution import measure_resolution

    def fn(source: Array, target: Array, rng: np.random.Generator) -> Array:
        T = coarse(source, target, rng)
        norm = fit_normalization(source, target)
        src, tgt = norm.to_unit(source), norm.to_unit(target)
        refined = icp(src, tgt, norm.transform_to_unit(T), measure_resolution(src, tgt))
        return norm.transform_to_world(refined.transform)

    return fn


def baseline_method(fn: Callable[[Array, Array, np.random.Generator], Array]) -> MethodFn:
    def run(pair: Pair, seed: int) -> Outcome:
        rng = np.random.default_rng(seed)
        t0 = time.perf_counter()
        T = fn(pair.source, pair.target, rng)
        return Outcome(np.asarray(T, dtype=np.float64), (time.perf_counter() - t0) * 1e3)

    return run


def request_body(
    pair: Pair,
    seed: int,
    icp: bool = True,
    steps: Sequence[int] | None = None,
    adaptive: bool = False,
    fine_matching: bool = False,
) -> bytes:
    """``adaptive``: the service's default request (exit checks, global match, rescues, the walk, the polish, the
    robust ICP); else the paper's v2: a network call for every step, then least-squares ICP, nothing else, and
    with ``fine_matching`` the fine phase's call, as ``PAPER_V2`` in process takes it where the model has one."""
    from pranet.core.registration_config import PAPER_AGENT_POINTS, SERVICE_DEFAULT
    from pranet.core.wire import encode_cloud

    body: dict[str, Any] = {
        "source": encode_cloud(pair.source),
        "target": encode_cloud(pair.target),
        "icp": icp,
        "seed": seed,
        "return_trajectory": False,
        "exit_checks": list(SERVICE_DEFAULT.exit_checks) if adaptive else [],
        "rescue": adaptive,
        "global_match": adaptive,
        "walk": adaptive,
        "polish": adaptive,
        "robust_icp": adaptive,
    }
    if not adaptive:
        body["agent_points"] = PAPER_AGENT_POINTS  # as the paper's v2 in process
        body["fine_matching"] = fine_matching
    if steps is not None:
        body["steps"] = list(steps)
    return json.dumps(body).encode()


def http_method(
    client: Any, steps: Sequence[int] | None = None, adaptive: bool = False, fine_matching: bool = False
) -> MethodFn:
    """``pranet-v2`` (or the adaptive variant) over HTTP; the latency is the client's: encoding, request, parsing."""

    def run(pair: Pair, seed: int) -> Outcome:
        t0 = time.perf_counter()
        body = request_body(pair, seed, steps=steps, adaptive=adaptive, fine_matching=fine_matching)
        r = client.post("/register", content=body, headers={"Content-Type": "application/json"})
        if r.status_code != 200:
            raise RuntimeError(f"HTTP {r.status_code}: {r.text[:300]}")
        data = r.json()
        ms = (time.perf_counter() - t0) * 1e3
        extra = {
            "server_timing_ms": data["timing_ms"],
            "exit_checks": data.get("exit_checks", []),
            "network_calls": data.get("network_calls"),
        }
        return Outcome(np.asarray(data["transform"], dtype=np.float64), ms, extra)

    return run
