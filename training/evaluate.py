"""``pranet-eval``: PRANet-v1/v2 and the classical baselines on the unseen-category ModelNet40 test set.

The protocol of the paper's Tables 1-3 (RPMNet's metrics): the 1266 test shapes of categories 20-39
(``--limit N`` takes the first N, after ``--skip M``: a run in parts, each part on its own pairs of the whole run),
one registration problem per shape built by
``make_pair(shape, setting, pair_rng(seed, setting, i), max_angle, 0.5, rotation)`` so that every
method sees the same pairs. PRANet runs the agent once per pair: pranet-v1 is its result, pranet-v2
the same result refined by ICP (timed as agent + ICP). Per pair: isotropic rotation error (degrees),
translation error, clean L2, modified Chamfer distance, success (rotation < 1° and translation <
0.01) and wall time (ms). The table puts the paper's numbers beside ours; ``--json`` keeps
everything; ``--plot`` draws the paper's Fig. 5 (Chamfer distance and angle over the agent's steps).

Examples::

    pranet-eval --setting noisy --limit 100 --json runs/eval/noisy.json
    pranet-eval --setting clean --skip 633 --json runs/eval/clean-2.json   # the second half, beside the first
    pranet-eval --setting clean --methods pranet-v1 --policy stoch1 --json runs/eval/stoch1.json
    pranet-eval --setting clean --rotation naive --max-angle 32 --methods pranet-v1 --json naive.json
    pranet-eval --setting clean --methods pranet-v1 --plot fig5.png --json fig5.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pranet.core.agent import POLICIES
from pranet.core.metrics import SUCCESS_ROTATION_DEG, SUCCESS_TRANSLATION, chamfer, evaluate_pair, isotropic_errors
from pranet.core.se3 import Array, apply_transform
from pranet.training.reporting import environment, json_default, nan_to_none
from pranet.training.samples import SETTINGS, Pair, make_pair, pair_rng

# pranet-adaptive: v2 with the service's exit checks and rescue (beyond the paper; core.pipeline.register)
PRANET_METHODS = ("pranet-v1", "pranet-v2", "pranet-adaptive")
BASELINE_METHODS = ("icp", "fgr", "ransac")
ALL_METHODS = PRANET_METHODS + BASELINE_METHODS
METRICS = ("rotation_deg", "translation", "l2", "mcd")

# The paper's numbers (AAAI 2022, Tables 1-3: mean isotropic rotation error in degrees, translation
# error, clean L2, modified Chamfer distance; FGR* used clean mesh normals, our FGR estimated ones).
PAPER: dict[str, dict[str, dict[str, float]]] = {
    "clean": {
        "icp": {"rotation_deg": 5.872, "translation": 0.0463, "l2": 0.0507, "mcd": 0.00215},
        "fgr": {"rotation_deg": 0.052, "translation": 0.000407, "l2": 0.000342, "mcd": 0.000107},
        "pranet-v1": {"rotation_deg": 1.554, "translation": 0.0246, "l2": 0.0249, "mcd": 0.00131},
        "pranet-v2": {"rotation_deg": 0.045, "translation": 0.000471, "l2": 0.000254, "mcd": 0.0000043},
    },
    "noisy": {
        "icp": {"rotation_deg": 6.393, "translation": 0.0474, "l2": 0.0517, "mcd": 0.00221},
        "fgr": {"rotation_deg": 3.879, "translation": 0.0307, "l2": 0.0322, "mcd": 0.00270},
        "pranet-v1": {"rotation_deg": 5.083, "translation": 0.0448, "l2": 0.0457, "mcd": 0.00183},
        "pranet-v2": {"rotation_deg": 2.900, "translation": 0.0207, "l2": 0.0213, "mcd": 0.000768},
    },
    "partial": {
        "icp": {"rotation_deg": 24.692, "translation": 0.251, "l2": 0.270, "mcd": 0.0134},
        "fgr": {"rotation_deg": 73.734, "translation": 0.477, "l2": 0.540, "mcd": 0.0447},
        "pranet-v1": {"rotation_deg": 8.902, "translation": 0.119, "l2": 0.124, "mcd": 0.00625},
        "pranet-v2": {"rotation_deg": 7.237, "translation": 0.0759, "l2": 0.0785, "mcd": 0.00239},
    },
}
# Table 4: average inference time (ms) on a Xeon E5-2650 v3 + GTX Titan X (PRANet on the GPU).
PAPER_TIME_MS: dict[str, float] = {"icp": 131.0, "fgr": 157.0, "pranet-v1": 742.0}
# Fig. 5's caption: the initial Chamfer distance and angle (step 0, left out of the plot).
PAPER_FIG5_INITIAL: dict[str, float] = {"chamfer": 0.199, "angle_deg": 43.7}
# Ablations, all PRANet-v1 on the clean set. Table "Stochasticity of the policy":
PAPER_POLICY: dict[str, dict[str, float]] = {
    "deterministic": {"rotation_deg": 1.554, "translation": 0.0246, "l2": 0.0249, "mcd": 0.00131},
    "stoch1": {"rotation_deg": 1.550, "translation": 0.0248, "l2": 0.0250, "mcd": 0.00132},
    "stoch2": {"rotation_deg": 3.669, "translation": 0.0544, "l2": 0.0556, "mcd": 0.00484},
}
# Table "Sampling rotations" (test set: naive Euler sampling up to 32° per axis), by training sampling:
PAPER_SAMPLING: dict[str, dict[str, float]] = {
    "isotropic": {"rotation_deg": 1.555, "translation": 0.0240, "l2": 0.0247, "mcd": 0.00129},
    "naive": {"rotation_deg": 2.771, "translation": 0.0302, "l2": 0.0307, "mcd": 0.00128},
}


def paper_reference(
    setting: str, method: str, policy: str = "deterministic", rotation: str = "isotropic", trained_rotation: str = ""
) -> dict[str, float] | None:
    """The paper's row comparable to ``method`` under this configuration, or ``None``."""
    if method == "pranet-v1" and setting == "clean" and rotation == "naive":
        return PAPER_SAMPLING.get(trained_rotation or "isotropic")
    if rotation != "isotropic":
        return None
    if method == "pranet-v1" and setting == "clean" and policy != "deterministic":
        return PAPER_POLICY[policy]
    if method.startswith("pranet") and policy != "deterministic":
        return None
    return PAPER.get(setting, {}).get(method)


# --------------------------------------------------------------------------------------------------
# Methods. A runner maps (pair, generator) to {method name: MethodOutput} for its ``methods``; one
# runner may produce several (the PRANet runner gives v1 and v2 from one agent run).


@dataclass
class MethodOutput:
    transform: Array  # (4, 4) T_target_source
    ms: float
    trajectory: list[Array] = field(default_factory=list)  # per-step T_target_source (PRANet only)
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Runner:
    methods: tuple[str, ...]
    fn: Callable[[Pair, np.random.Generator], dict[str, MethodOutput]]


def runner_key(runner: Runner) -> int:
    """The seed word of ``runner``'s randomness: from the names of its methods, not its place in the list."""
    return zlib.crc32("+".join(runner.methods).encode())


def pranet_runner(
    engine: Any,
    methods: Sequence[str] = PRANET_METHODS,
    policy: str = "deterministic",
    early_stop: bool = False,
    fine_matching: bool | None = None,
) -> Runner:
    """PRANet through ``engine`` (``pranet.engine.Engine``): v1 and v2 from one ``PAPER_V2`` registration (its
    agent-only and refined poses), the adaptive variant as the service's default (``SERVICE_DEFAULT``).
    ``fine_matching``: whether the paper's agent makes the fine phase's call (``RegistrationConfig.fine_matching``;
    ``None``: when the model has one)."""
    from pranet.core.confidence import estimate_confidence
    from pranet.core.registration_config import PAPER_V1, PAPER_V2, SERVICE_DEFAULT

    options = {"policy": policy, "early_stop": early_stop}
    want_v2 = "pranet-v2" in methods
    want_paper = "pranet-v1" in methods or want_v2
    paper_config = (PAPER_V2 if want_v2 else PAPER_V1).with_(**options, fine_matching=fine_matching)
    adaptive_config = SERVICE_DEFAULT.with_(**options)

    def run(pair: Pair, rng: np.random.Generator) -> dict[str, MethodOutput]:
        out: dict[str, MethodOutput] = {}
        if "pranet-adaptive" in methods:
            # Its own run, from the same generator state as the paper's v1/v2 run below.
            a_rng = np.random.default_rng(rng.bit_generator.seed_seq) if want_paper else rng
            reg = engine.register(pair.source, pair.target, adaptive_config, a_rng)
            extra = {
                "timing_ms": reg.timing_ms,
                "n_steps": len(reg.trajectory),
                "checks": reg.checks,
                "rescued": reg.rescued,
                "confidence": reg.confidence.score,
                "status": reg.confidence.status,
            }
            traj = [T for _, _, T in reg.trajectory]
            out["pranet-adaptive"] = MethodOutput(reg.T_target_source, reg.timing_ms["total"], traj, extra)
        if not want_paper:
            return out
        reg = engine.register(pair.source, pair.target, paper_config, rng)
        traj = [T for _, _, T in reg.trajectory]
        t = reg.timing_ms
        v1_ms = t["preprocess"] + t["target_embedding"] + t["agent_steps"]  # timed as the paper: no confidence
        extra: dict[str, Any] = {"timing_ms": t, "n_steps": len(traj), "network_calls": reg.network_calls}
        if reg.agent is not None and reg.agent.stopped_early:
            extra["stopped_early"] = list(reg.agent.stopped_early)
        if "pranet-v1" in methods:
            agent_conf = reg.confidence  # the run's own when it has no ICP; else the agent's result scored here
            if want_v2:
                norm = reg.normalization
                T_agent = norm.transform_to_unit(reg.agent_T_target_source)
                agent_conf = estimate_confidence(norm.to_unit(pair.source), norm.to_unit(pair.target), T_agent)
            v1_extra = {**extra, "confidence": agent_conf.score, "status": agent_conf.status}
            out["pranet-v1"] = MethodOutput(reg.agent_T_target_source, v1_ms, traj, v1_extra)
        if want_v2:
            v2_extra = {
                **extra,
                "icp_ms": t["icp"],
                "icp_fitness": reg.icp.fitness if reg.icp is not None else None,
                "confidence": reg.confidence.score,
                "status": reg.confidence.status,
            }
            out["pranet-v2"] = MethodOutput(reg.T_target_source, v1_ms + t["icp"], traj, v2_extra)
        return out

    return Runner(tuple(m for m in PRANET_METHODS if m in methods), run)


def baseline_runner(name: str, fn: Callable[..., Array]) -> Runner:
    def run(pair: Pair, rng: np.random.Generator) -> dict[str, MethodOutput]:
        t0 = time.perf_counter()
        T = fn(pair.source, pair.target, rng)
        return {name: MethodOutput(np.asarray(T, dtype=np.float64), (time.perf_counter() - t0) * 1e3)}

    return Runner((name,), run)


# --------------------------------------------------------------------------------------------------
# Evaluation loop, summaries, Fig. 5.


def pair_digest(pair: Pair) -> str:
    """A short hash of the pair's arrays: records of different methods on the same pair share it."""
    h = hashlib.sha1()
    for a in (pair.source, pair.target, pair.T_gt):
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


def step_curves(pair: Pair, trajectory: Sequence[Array], n_steps: int) -> tuple[list[float], list[float]]:
    """Fig. 5's per-step values: Chamfer distance (source under each step's transform vs the target) and
    the isotropic rotation error (degrees), for steps 0 (identity) .. ``n_steps``; a trajectory cut
    short by early stopping holds its last pose."""
    poses = [np.eye(4), *trajectory]
    poses += [poses[-1]] * (n_steps + 1 - len(poses))
    cd = [chamfer(apply_transform(T, pair.source), pair.target) for T in poses[: n_steps + 1]]
    angle = [isotropic_errors(T, pair.T_gt)[0] for T in poses[: n_steps + 1]]
    return cd, angle


def _finite_mean(x: np.ndarray) -> float:
    return float(np.mean(x)) if len(x) else math.nan


def summarize(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Means (the paper's statistic), medians, success rate and timing over one method's records."""
    out: dict[str, Any] = {"n": len(records), "n_errors": sum(1 for r in records if r.get("error"))}
    for m in METRICS:
        x = np.array([r[m] for r in records], dtype=np.float64)
        out[m] = _finite_mean(x)
        out[f"{m}_median"] = float(np.median(x)) if len(x) else math.nan
    out["success_rate"] = _finite_mean(np.array([r["success"] for r in records], dtype=np.float64))
    ms = np.array([r["ms"] for r in records], dtype=np.float64)
    ms = ms[np.isfinite(ms)]  # failed runs have no time
    out["ms_mean"] = _finite_mean(ms)
    out["ms_median"] = float(np.median(ms)) if len(ms) else math.nan
    return out


def curve_summary(curves: np.ndarray) -> dict[str, list[float]]:
    """``curves: (n_pairs, n_steps + 1)`` -> mean and a normal-approximation 95 % confidence band."""
    mean = curves.mean(axis=0)
    half = 1.96 * curves.std(axis=0, ddof=1) / np.sqrt(len(curves)) if len(curves) > 1 else np.zeros_like(mean)
    return {"mean": mean.tolist(), "ci_low": (mean - half).tolist(), "ci_high": (mean + half).tolist()}


def plot_fig5(fig5: dict[str, Any], path: Path, switch_step: int, title: str = "") -> None:
    """The paper's Fig. 5: Chamfer distance and angle over the iterations (step 0 left out, as there)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, key, label in ((axes[0], "chamfer", "Chamfer distance"), (axes[1], "angle_deg", "angle (°)")):
        c = fig5[key]
        steps = np.arange(1, len(c["mean"]))
        ax.fill_between(steps, c["ci_low"][1:], c["ci_high"][1:], color="gold", alpha=0.5, lw=0, label="95% CI")
        ax.plot(steps, c["mean"][1:], color="tab:blue", lw=1.5, label="mean")
        ax.axvline(switch_step, color="k", ls=":", lw=1.2, label="coarse → fine")
        ax.set_xlabel("iteration")
        ax.set_ylabel(label)
        ax.set_xlim(1, steps[-1] if len(steps) else 1)
        ax.set_title(f"{label} (initial {c['mean'][0]:.3g}, not shown)", fontsize=9)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=150)
    plt.close(fig)


def evaluate(
    shapes: np.ndarray,
    setting: str,
    runners: Sequence[Runner],
    seed: int = 1234,
    max_angle_deg: float = 60.0,
    rotation: str = "isotropic",
    curves_for: str | None = None,
    n_curve_steps: int = 60,
    shape_ids: Sequence[int] | None = None,
    progress: bool = True,
    first_pair: int = 0,
) -> dict[str, Any]:
    """Run every runner on pair ``i`` of ``shapes`` (``(S, P, 3)``) for ``i < S``.

    Returns ``{"records": {method: [per-pair dict]}, "summary": {method: ...}, "fig5": ...}``. The
    pair ``i`` is ``make_pair(shapes[i], setting, pair_rng(seed, setting, first_pair + i), ...)`` (``first_pair``:
    where ``shapes`` starts in the test list, so that a run in parts draws the whole run's pairs); each method's
    own randomness comes from ``default_rng([seed, setting, i, runner_key(runner)])``, so a method's answers do not
    depend on which others run beside it.
    """
    from tqdm import tqdm

    s_idx = SETTINGS.index(setting)
    records: dict[str, list[dict[str, Any]]] = {}
    cd_curves: list[list[float]] = []
    angle_curves: list[list[float]] = []
    bar = tqdm(range(len(shapes)), desc=f"pranet-eval {setting}", file=sys.stderr, disable=not progress)
    for k in bar:
        i = first_pair + k
        pair = make_pair(shapes[k], setting, pair_rng(seed, setting, i), max_angle_deg, 0.5, rotation)
        digest = pair_digest(pair)
        for runner in runners:
            rng = np.random.default_rng([seed, s_idx, i, runner_key(runner)])
            try:
                outputs = runner.fn(pair, rng)
            except Exception as e:  # a failed registration counts, as the identity, and is reported
                err = {"error": f"{type(e).__name__}: {e}"}
                outputs = {m: MethodOutput(np.eye(4), math.nan, extra=err) for m in runner.methods}
            for name, out in outputs.items():
                metrics = evaluate_pair(pair.source, pair.target, pair.clean_source, out.transform, pair.T_gt)
                rec: dict[str, Any] = {
                    "pair": i,
                    "shape": int(shape_ids[k]) if shape_ids is not None else i,
                    "pair_sha1": digest,
                    **metrics.as_dict(),
                    "ms": out.ms,
                    "T_est": np.round(out.transform, 10).tolist(),
                    "T_gt": pair.T_gt.tolist(),
                    **out.extra,
                }
                records.setdefault(name, []).append(rec)
                if curves_for is not None and name == curves_for:
                    cd, ang = step_curves(pair, out.trajectory, n_curve_steps)
                    cd_curves.append(cd)
                    angle_curves.append(ang)
        if "pranet-v1" in records:
            bar.set_postfix(v1_rot=f"{np.mean([r['rotation_deg'] for r in records['pranet-v1']]):.2f}")
    result: dict[str, Any] = {"records": records, "summary": {m: summarize(r) for m, r in records.items()}}
    if cd_curves:
        result["fig5"] = {
            "method": curves_for,
            "n_pairs": len(cd_curves),
            "chamfer": curve_summary(np.array(cd_curves)),
            "angle_deg": curve_summary(np.array(angle_curves)),
            "paper_initial": PAPER_FIG5_INITIAL,
        }
    return result


# --------------------------------------------------------------------------------------------------
# Output.


def _fmt(x: float | None, digits: int = 4) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return f"{x:.{digits}g}"


def format_table(summary: dict[str, Any], paper: dict[str, Any]) -> str:
    """Paper-style table: our means (and median rotation), success, timing; the paper's numbers beside."""
    head = (
        f"{'method':<15} {'rot':>8} {'rot med':>8} {'trans':>9} {'L2':>9} {'MCD':>9} {'succ %':>7} "
        f"{'med ms':>8} {'mean ms':>8} | {'paper rot':>9} {'trans':>8} {'L2':>8} {'MCD':>9} {'ms':>5}"
    )
    lines = [head, "-" * len(head)]
    for name, s in summary.items():
        p = paper.get(name) or {}
        lines.append(
            f"{name:<15} {_fmt(s['rotation_deg']):>8} {_fmt(s['rotation_deg_median']):>8} {_fmt(s['translation']):>9} "
            f"{_fmt(s['l2']):>9} {_fmt(s['mcd']):>9} {100 * s['success_rate']:>7.1f} {s['ms_median']:>8.1f} "
            f"{s['ms_mean']:>8.1f} | {_fmt(p.get('rotation_deg')):>9} {_fmt(p.get('translation')):>8} "
            f"{_fmt(p.get('l2')):>8} {_fmt(p.get('mcd')):>9} {_fmt(p.get('ms'), 3):>5}"
        )
    return "\n".join(lines)


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="pranet-eval",
        description="Evaluate PRANet-v1/v2 and ICP/FGR/RANSAC baselines on the unseen ModelNet40 categories.",
    )
    p.add_argument("--setting", choices=SETTINGS, default="clean")
    p.add_argument("--limit", type=int, default=None, help="first N of the 1266 test shapes (default: all)")
    p.add_argument(
        "--skip", type=int, default=0, help="start at this test shape, with its own pair (a run in parts; default 0)"
    )
    p.add_argument("--model", default=None, help="model directory (default: the model shipped in the package)")
    p.add_argument("--json", type=Path, default=None, help="write config, summaries and per-pair records here")
    p.add_argument(
        "--methods",
        default=",".join(ALL_METHODS),
        help=f"comma-separated subset of {','.join(ALL_METHODS)} (default: all)",
    )
    p.add_argument("--seed", type=int, default=1234, help="seed of the test pairs (default 1234, the paper's)")
    p.add_argument("--plot", type=Path, default=None, help="write the Fig. 5 curves (PNG) of pranet-v1's steps")
    p.add_argument("--policy", choices=POLICIES, default="deterministic")
    p.add_argument("--early-stop", action="store_true", help="end a scale once no action has a positive reward")
    p.add_argument(
        "--fine-matching",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="pranet-v1/v2: the fine phase's network call (score_fine.onnx: position-led rounds in the clouds' "
        "actual placement) instead of the trained one; default: on when the model has it. --no-fine-matching: the "
        "trained call in both phases (the tables before model 2.2.0's fine call)",
    )
    p.add_argument("--max-angle", type=float, default=60.0, help="max rotation (degrees; per axis for naive)")
    p.add_argument("--rotation", choices=("isotropic", "naive"), default="isotropic")
    p.add_argument("--data-dir", default=None, help="data root (default: $PRANET_DATA_DIR, else ../shared/data)")
    p.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads and OMP_NUM_THREADS")
    p.add_argument(
        "--icp-distance",
        type=float,
        default=None,
        help="max correspondence distance of the ICP-from-identity baseline (default: baselines.ICP_MAX_DISTANCE)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = sorted(set(methods) - set(ALL_METHODS))
    if unknown or not methods:
        p.error(f"--methods: unknown {unknown}; choose from {','.join(ALL_METHODS)}")
    args.methods = [m for m in ALL_METHODS if m in methods]
    if args.limit is not None and args.limit < 1:
        p.error("--limit must be at least 1")
    return args


def load_test_shapes(args: argparse.Namespace) -> tuple[Any, np.ndarray, np.ndarray, Path]:
    """``(test data, chosen shape indices, their points, data root)``: unseen categories, first ``--limit``."""
    from pranet.training.data import data_dir, load_modelnet40, test_indices

    root = data_dir(args.data_dir)
    data = load_modelnet40(root, "test")
    idx = test_indices(data.labels)
    idx = idx[args.skip :]
    if args.limit is not None:
        idx = idx[: args.limit]
    return data, idx, data.points[idx], root


@dataclass
class Methods:
    """The runners of one ``pranet-eval`` run and what the report says about them."""

    runners: list[Runner] = field(default_factory=list)
    model_info: dict[str, Any] | None = None
    trained_rotation: str = ""
    switch_step: int = 20
    n_steps: int = 60
    baseline_params: dict[str, Any] = field(default_factory=dict)


def build_methods(args: argparse.Namespace) -> Methods:
    """PRANet through the engine (one runner for v1, v2 and the adaptive variant), then the baselines."""
    m = Methods()
    pranet = [name for name in args.methods if name in PRANET_METHODS]
    if pranet:
        from pranet.core.registration_config import PAPER_V1
        from pranet.engine.engine import Engine

        engine = Engine.load(args.model, threads=args.threads)
        scorer = engine.scorer
        m.model_info = {**scorer.info(), "dir": str(args.model or "default"), "n_points": scorer.n_points}
        m.model_info["training"] = scorer.card.get("training")
        m.trained_rotation = scorer.card.get("config", {}).get("sampling", {}).get("rotation", "")
        m.switch_step, m.n_steps = int(scorer.schedule[0]), int(sum(scorer.schedule))
        m.runners.append(pranet_runner(engine, pranet, args.policy, args.early_stop, args.fine_matching))
        # As run, for the JSON's config and the header.
        args.fine_matching = PAPER_V1.with_(fine_matching=args.fine_matching).uses_fine_call(scorer.has_fine_call)
    if any(name in BASELINE_METHODS for name in args.methods):
        from functools import partial

        from pranet.training import baselines

        fns = dict(baselines.BASELINES)
        icp_distance = args.icp_distance if args.icp_distance is not None else baselines.ICP_MAX_DISTANCE
        fns["icp"] = partial(baselines.icp, max_distance=icp_distance)
        m.baseline_params = {
            "icp_max_distance": icp_distance,
            "refine_max_distance": baselines.REFINE_MAX_DISTANCE,
            "icp_max_iterations": baselines.ICP_MAX_ITERATIONS,
            "voxel": baselines.VOXEL,
            "normals": f"estimated: PCA over {baselines.NORMAL_KNN} nearest neighbours, oriented outwards",
            "fpfh_radius": baselines.FPFH_RADIUS,
            "ransac": [baselines.RANSAC_MAX_ITERATIONS, baselines.RANSAC_CONFIDENCE],
        }
        m.runners += [baseline_runner(name, fns[name]) for name in BASELINE_METHODS if name in args.methods]
    return m


def paper_rows(args: argparse.Namespace, trained_rotation: str) -> dict[str, dict[str, float]]:
    """The paper's row beside each method (with Table 4's time where it has one)."""
    paper = {
        m: ref
        for m in args.methods
        if (ref := paper_reference(args.setting, m, args.policy, args.rotation, trained_rotation)) is not None
    }
    return {m: {**ref, **({"ms": PAPER_TIME_MS[m]} if m in PAPER_TIME_MS else {})} for m, ref in paper.items()}


def write_json(args: argparse.Namespace, data: Any, idx: np.ndarray, root: Path, m: Methods, out: dict) -> None:
    config = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    config.update(
        data_root=str(root),
        data_files=[str(f) for f in data.files],
        n_pairs=len(idx),
        translation_max=0.5,
        pair_generator="make_pair(shape, setting, pair_rng(seed, setting, i), max_angle, 0.5, rotation)",
        baselines=m.baseline_params,
    )
    doc = {"config": config, "model": m.model_info, "environment": environment(args.threads), **out}
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(nan_to_none(doc), default=json_default, indent=1))
    print(f"pranet-eval: wrote {args.json}", file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    # Open3D reads OMP_NUM_THREADS when it is first imported (nothing below has imported it yet in a CLI run).
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    # 1. The pairs and the methods.
    data, idx, shapes, root = load_test_shapes(args)
    m = build_methods(args)
    plot = args.plot is not None and "pranet-v1" in args.methods
    if args.plot is not None and not plot:
        print("pranet-eval: --plot needs pranet-v1 among --methods; no plot", file=sys.stderr)
    # 2. Every method on every pair.
    t0 = time.perf_counter()
    result = evaluate(
        shapes,
        args.setting,
        m.runners,
        seed=args.seed,
        max_angle_deg=args.max_angle,
        rotation=args.rotation,
        curves_for="pranet-v1" if plot else None,
        n_curve_steps=m.n_steps,
        shape_ids=idx,
        progress=not args.quiet,
        first_pair=args.skip,
    )
    wall_s = time.perf_counter() - t0
    # 3. The table, the figure, the JSON.
    paper = paper_rows(args, m.trained_rotation)
    summary = {name: result["summary"][name] for name in args.methods if name in result["summary"]}
    model_str = f"{m.model_info['name']} {m.model_info['version']}" if m.model_info else "-"
    print(
        f"\nsetting={args.setting} pairs={len(idx)} seed={args.seed} rotation={args.rotation} <= {args.max_angle}° "
        f"policy={args.policy}{' early-stop' if args.early_stop else ''}"
        f"{' fine-matching' if args.fine_matching else ''} model={model_str}  (success: rot < "
        f"{SUCCESS_ROTATION_DEG}° and trans < {SUCCESS_TRANSLATION}; means over pairs; paper: AAAI 2022 Tables 1-4)"
    )
    print(format_table(summary, paper))
    if plot and "fig5" in result:
        name = m.model_info["name"] if m.model_info else ""
        plot_fig5(result["fig5"], args.plot, m.switch_step, f"PRANet-v1, {args.setting}, {len(idx)} pairs ({name})")
        print(f"pranet-eval: wrote {args.plot}", file=sys.stderr)
    if args.json is not None:
        out = {"wall_s": wall_s, "summary": summary, "paper": paper, "fig5": result.get("fig5")}
        write_json(args, data, idx, root, m, {**out, "records": result["records"]})
    return 0


if __name__ == "__main__":
    sys.exit(main())
