"""``pranet-client``: register two point cloud files through a running ``pranet-serve``.

    pranet-client register SOURCE TARGET [--url URL] [--api-key KEY] [--no-icp] [--json]
                                         [--save-aligned OUT] [--plot OUT.png] [--init global]
    pranet-client register-many PAIRS.csv --out results.jsonl [--concurrency K] [--shard-index I --shard-count N]
    pranet-client health | ready | model [--url URL]

The printed transform is ``T_target_source``: ``target ≈ R @ source + t``. Every failure (server
unreachable, unreadable file, HTTP error) is one ``error: ...`` line on stderr and exit status 1;
bad arguments exit with status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from pranet.client.batch import RetryPolicy
from pranet.client.client import DEFAULT_URL, PranetClient, PranetError, RegistrationResult
from pranet.client.io import SUPPORTED_SUFFIXES, PointCloudIOError, read_point_cloud, write_point_cloud
from pranet.core.se3 import apply_transform, rotation_angle

URL_ENV = "PRANET_URL"
API_KEY_ENV = "PRANET_API_KEY"
PLOT_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg")
PLOT_POINTS = 3000  # points per cloud drawn in the 3-D scatter plots
LIMITS_HELP = (
    "Size limits: the service refuses (413) clouds over its point limit (1,200,000 per cloud by default, "
    "PRANET_MAX_POINTS) and JSON-list clouds over 200,000 points (PRANET_MAX_LIST_POINTS); this client sends clouds "
    "over 5000 points base64-encoded, so only the point limit applies. Downsample larger clouds first."
)


class CliError(Exception):
    """A user-facing error detected by the CLI itself (bad output path, ...)."""


def rotation_angle_deg(R: npt.ArrayLike) -> float:
    return float(np.degrees(rotation_angle(R)))


def _common_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--url",
        default=os.environ.get(URL_ENV, DEFAULT_URL),
        help=f"service base URL (default: ${URL_ENV} or {DEFAULT_URL})",
    )
    parser.add_argument(
        "--api-key",
        default=os.environ.get(API_KEY_ENV),
        help=f"bearer token, when the service was started with one (default: ${API_KEY_ENV})",
    )
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds per request (default: 120)")


def _positive(text: str) -> int:
    return _int_at_least(text, 1)


def _non_negative(text: str) -> int:
    return _int_at_least(text, 0)


def _int_at_least(text: str, low: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < low:
        raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
    return value


def _step_counts(text: str) -> list[int]:
    try:
        counts = [int(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers such as 20,40, got {text!r}") from None
    if any(c < 0 for c in counts):
        raise argparse.ArgumentTypeError(f"step counts must be >= 0, got {text!r}")
    return counts


def _registration_options(parser: argparse.ArgumentParser) -> None:
    """The request's options, shared by register and register-many."""
    parser.add_argument(
        "--policy", help="agent policy: deterministic, stoch1 or stoch2 (server default: deterministic)"
    )
    parser.add_argument("--seed", type=int, help="seed of the server's resampling and stochastic policies")
    parser.add_argument(
        "--steps",
        type=_step_counts,
        metavar="N[,N...]",
        help="agent steps per step-size scale, e.g. 20,40 (server default: the model's schedule; 0,0 = ICP only)",
    )
    parser.add_argument("--early-stop", action="store_true", default=None, help="stop the agent when it converges")
    checks = parser.add_mutually_exclusive_group()
    checks.add_argument(
        "--exit-checks",
        type=_step_counts,
        metavar="N[,N...]",
        help="ICP after these many agent steps; stop once converged (server default: 20,40)",
    )
    checks.add_argument(
        "--all-steps",
        dest="exit_checks",
        action="store_const",
        const=[],
        help="no exit checks: run every agent step, then ICP (the paper's PRANet-v2)",
    )
    parser.add_argument(
        "--no-rescue",
        dest="rescue",
        action="store_false",
        default=None,
        help="no rescues of a suspect result (restarts around the best estimate, wide-window ICP)",
    )
    parser.add_argument(
        "--no-global-match",
        dest="global_match",
        action="store_false",
        default=None,
        help="do not try the classical global match when the agent is not confident",
    )
    parser.add_argument(
        "--paper-steps",
        dest="walk",
        action="store_false",
        default=None,
        help="a network call per agent step, as the paper (default: walk toward each estimate between calls)",
    )
    parser.add_argument(
        "--fine-matching",
        dest="fine_matching",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="with --paper-steps: the fine steps' own network call, matching the clouds where the agent has put "
        "them (nearer the truth on partial overlap; the server's default where the model has it); "
        "--no-fine-matching: the trained call in both phases",
    )
    parser.add_argument(
        "--no-polish",
        dest="polish",
        action="store_false",
        default=None,
        help="do not refine the winning result once more (generalized ICP on dense scans, robust ICP on sparse ones)",
    )
    parser.add_argument(
        "--least-squares-icp",
        dest="robust_icp",
        action="store_false",
        default=None,
        help="ICP by least squares on sparse clouds, as the paper's v2 (default: a robust kernel there)",
    )
    parser.add_argument(
        "--init",
        choices=("identity", "global"),
        help="agent start: identity (server default; rotations up to 60°) or global (many starts, any rotation)",
    )
    parser.add_argument(
        "--starts", type=int, metavar="N", help="number of start rotations with --init global (default 24)"
    )


def _options_of(args: argparse.Namespace) -> dict[str, Any]:
    """The request options ``args`` asked for; ``None`` = the server's default."""
    return {
        "policy": args.policy,
        "seed": args.seed,
        "steps": args.steps,
        "early_stop": args.early_stop,
        "exit_checks": args.exit_checks,
        "rescue": args.rescue,
        "global_match": args.global_match,
        "walk": args.walk,
        "fine_matching": args.fine_matching,
        "polish": args.polish,
        "robust_icp": args.robust_icp,
        "init": args.init,
        "starts": args.starts,
    }


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pranet-client",
        description="Client of the PRANet point cloud registration service.",
        epilog=LIMITS_HELP,
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    reg = sub.add_parser(
        "register",
        help="register SOURCE onto TARGET and print T_target_source",
        description="Register SOURCE onto TARGET. Prints T_target_source (target ≈ R @ source + t). "
        f"Files: {', '.join(SUPPORTED_SUFFIXES)}.",
        epilog=LIMITS_HELP,
    )
    reg.add_argument("source", type=Path, help="the cloud that is moved")
    reg.add_argument("target", type=Path, help="the cloud it is aligned to")
    _common_options(reg)
    reg.add_argument("--no-icp", dest="icp", action="store_false", help="skip the ICP refinement (PRANet-v1)")
    reg.add_argument("--json", action="store_true", help="print the raw JSON response instead of a summary")
    reg.add_argument("--save-aligned", type=Path, metavar="OUT", help="write the transformed source to OUT")
    reg.add_argument("--plot", type=Path, metavar="OUT", help="draw the clouds before/after and per-step curves")
    _registration_options(reg)

    many = sub.add_parser(
        "register-many",
        help="register every pair of a CSV file into a JSON-lines file (resumable)",
        description="Register every pair of PAIRS (a CSV file with the columns source and target; optional id and "
        "T_target_source; other columns ignored; paths relative to the CSV's folder) into OUT, one JSON line per "
        "pair, written as each answer arrives. A rerun skips the pairs already in OUT, so a killed run resumes where "
        "it stopped. 502, 503 and connection errors are retried with exponential backoff; other errors are "
        "recorded in the pair's line and not retried.",
        epilog="Exit status: 0 every pair registered; 3 some pairs failed (their lines say why); 4 some pairs are "
        "not done (the service was unavailable after the retries): run the same command again to resume; "
        "1 the run could not start (unreadable CSV, ...); 2 bad arguments. " + LIMITS_HELP,
    )
    many.add_argument("pairs", type=Path, help="CSV file of pairs (the format of the real-scan pairs.csv)")
    many.add_argument("--out", type=Path, required=True, help="JSON-lines results file, appended to (created if new)")
    many.add_argument("--concurrency", type=_positive, default=4, metavar="K", help="pairs in flight (default: 4)")
    many.add_argument("--retries", type=_non_negative, default=5, metavar="N", help="retries per pair (default: 5)")
    many.add_argument("--shard-index", type=_non_negative, default=0, metavar="I", help="run the pairs i %% N == I")
    many.add_argument("--shard-count", type=_positive, default=1, metavar="N", help="number of shards (default: 1)")
    many.add_argument("--retry-errors", action="store_true", help="run again the pairs whose line in OUT is an error")
    many.add_argument("--quiet", action="store_true", help="no progress line (the summary is still printed)")
    _common_options(many)
    many.add_argument("--no-icp", dest="icp", action="store_false", help="skip the ICP refinement (PRANet-v1)")
    _registration_options(many)

    for name, text in (
        ("health", "check that the service process is up (GET /health)"),
        ("ready", "check that the model is loaded (GET /ready)"),
        ("model", "show the served model (GET /model)"),
    ):
        _common_options(sub.add_parser(name, help=text, description=text))
    return parser


def _check_output(path: Path | None, suffixes: tuple[str, ...], what: str) -> None:
    """Fail before the request, not after it, when an output path cannot be written."""
    if path is None:
        return
    if path.suffix.lower() not in suffixes:
        raise CliError(f"{path}: {what} must end in one of {', '.join(suffixes)}")
    if not path.parent.is_dir():
        raise CliError(f"{path}: folder {path.parent} does not exist")


def format_summary(result: RegistrationResult, source: Path, target: Path, n_source: int, n_target: int) -> str:
    T = result.transform
    lines = [f"source: {source} ({n_source} points) -> target: {target} ({n_target} points)"]
    if result.model:
        m = result.model
        lines.append(f"model: {m.get('name')} {m.get('version')} (sha256 {str(m.get('sha256', ''))[:12]})")
    lines.append("T_target_source (target ≈ R @ source + t):")
    lines.extend("  " + " ".join(f"{v:12.6f}" for v in row) for row in T)
    lines.append(f"rotation: {rotation_angle_deg(T[:3, :3]):.3f} deg, translation: {np.linalg.norm(T[:3, 3]):.6g}")
    icp = result.icp
    if icp and icp.get("applied"):
        lines.append(f"ICP: fitness {icp.get('fitness', float('nan')):.4f}, inlier_rmse {icp.get('inlier_rmse'):.6g}")
    else:
        lines.append("ICP: not applied")
    if result.confidence is not None or result.status is not None:
        parts = []
        if result.status is not None:
            parts.append(f"status: {result.status}")
        if result.confidence is not None:
            parts.append(f"confidence: {result.confidence:.3f}")
        if result.matches:  # converged on the global match's evidence, not on the confidence
            parts.append(f"certified by {result.matches} feature matches")
        if result.candidate is not None:
            parts.append(f"candidate: {result.candidate}")
        lines.append(", ".join(parts))
    if result.timing_ms:
        timing = ", ".join(f"{k} {float(v):.1f}" for k, v in result.timing_ms.items())
        lines.append(f"timing (ms): {timing}")
    return "\n".join(lines)


def plot_registration(
    path: Path, source: npt.ArrayLike, target: npt.ArrayLike, result: RegistrationResult, seed: int = 0
) -> Path:
    """Write ``registration_figure(...)`` to ``path`` (PNG)."""
    registration_figure(source, target, result, seed).savefig(path, dpi=100)
    return path


def registration_figure(source: npt.ArrayLike, target: npt.ArrayLike, result: RegistrationResult, seed: int = 0):
    """Source/target before and after (3-D scatter, subsampled) and per-step curves, as a matplotlib ``Figure``.

    The curves show each trajectory step's ``T_target_source`` against the final transform: the
    rotation angle of ``R_final^T R_step`` (degrees) and ``|t_step - t_final|`` (cloud units).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    rng = np.random.default_rng(seed)

    def subsample(p: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        return p if len(p) <= PLOT_POINTS else p[rng.choice(len(p), PLOT_POINTS, replace=False)]

    src = subsample(np.asarray(source, dtype=np.float64))
    tgt = subsample(np.asarray(target, dtype=np.float64))
    aligned = apply_transform(result.transform, src)

    # One cube of axis limits for both 3-D panels, so "before" and "after" compare at a glance.
    everything = np.concatenate([src, tgt, aligned])
    center = (everything.min(axis=0) + everything.max(axis=0)) / 2
    half = float((everything.max(axis=0) - everything.min(axis=0)).max()) / 2 or 1.0

    fig = Figure(figsize=(12, 9), layout="constrained")
    FigureCanvasAgg(fig)
    for i, (title, moved) in enumerate((("before (input)", src), ("after: T_target_source applied", aligned))):
        ax = fig.add_subplot(2, 2, i + 1, projection="3d")
        ax.scatter(*tgt.T, s=1, c="tab:blue", label="target", depthshade=False)
        ax.scatter(*moved.T, s=1, c="tab:orange", label="source", depthshade=False)
        ax.set_title(title)
        ax.set(xlim=(center[0] - half, center[0] + half), ylim=(center[1] - half, center[1] + half))
        ax.set_zlim(center[2] - half, center[2] + half)
        ax.set_box_aspect((1, 1, 1))
        ax.tick_params(labelsize=7)
        for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
            axis.set_major_locator(MaxNLocator(4))
        ax.legend(loc="upper right", markerscale=6)

    final = result.transform
    steps = list(range(len(result.trajectory) + 1))  # 0 = the agent's start, i = after the agent's i-th step
    start = result.initial_transform if result.initial_transform is not None else np.eye(4)
    transforms = [start] + [s.transform for s in result.trajectory]
    angles = [rotation_angle_deg(final[:3, :3].T @ T[:3, :3]) for T in transforms]
    offsets = [float(np.linalg.norm(T[:3, 3] - final[:3, 3])) for T in transforms]
    for j, (values, label) in enumerate(
        ((angles, "rotation to the final transform (deg)"), (offsets, "translation to the final transform"))
    ):
        ax = fig.add_subplot(2, 2, 3 + j)
        if result.trajectory:
            ax.plot(steps, values, marker=".", lw=1)
        else:
            ax.text(0.5, 0.5, "no trajectory in the response", ha="center", va="center", transform=ax.transAxes)
        ax.set_xlabel("agent steps taken (0 = the agent's start pose)")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    icp = result.icp or {}
    fig.suptitle(
        f"T_target_source: {rotation_angle_deg(final[:3, :3]):.2f} deg, |t| {np.linalg.norm(final[:3, 3]):.4g}"
        + (f"; ICP fitness {icp.get('fitness', 0.0):.3f}" if icp.get("applied") else "; no ICP")
        + (f"; confidence {result.confidence:.3f}" if result.confidence is not None else "")
        + (f" ({result.status})" if result.status else "")
    )
    return fig


def _register(args: argparse.Namespace, client: PranetClient) -> int:
    for p in (args.source, args.target):
        if p.suffix.lower() not in SUPPORTED_SUFFIXES and p.exists():
            raise CliError(f"{p}: unsupported file type; use one of {', '.join(SUPPORTED_SUFFIXES)}")
    _check_output(args.save_aligned, SUPPORTED_SUFFIXES, "--save-aligned")
    _check_output(args.plot, PLOT_SUFFIXES, "--plot")
    source = read_point_cloud(args.source)
    target = read_point_cloud(args.target)
    options = {**_options_of(args), "return_trajectory": True if args.plot else None}
    result = client.register(source, target, icp=args.icp, **options)
    if args.json:
        print(json.dumps(result.raw, indent=2))
    else:
        print(format_summary(result, args.source, args.target, len(source), len(target)))
    out = sys.stderr if args.json else sys.stdout
    if args.save_aligned:
        write_point_cloud(args.save_aligned, apply_transform(result.transform, source))
        print(f"aligned source written to {args.save_aligned}", file=out)
    if args.plot:
        plot_registration(args.plot, source, target, result)
        print(f"plot written to {args.plot}", file=out)
    return 0


def _register_many(args: argparse.Namespace, client: PranetClient) -> int:
    if args.shard_index >= args.shard_count:
        raise CliError(f"--shard-index {args.shard_index} must be less than --shard-count {args.shard_count}")
    if not args.out.parent.is_dir():
        raise CliError(f"{args.out}: folder {args.out.parent} does not exist")
    summary = client.register_many(
        args.pairs,
        args.out,
        args.concurrency,
        retry=RetryPolicy(retries=args.retries),
        shard_index=args.shard_index,
        shard_count=args.shard_count,
        retry_errors=args.retry_errors,
        progress=not args.quiet,
        icp=args.icp,
        return_trajectory=False,  # not kept in the results: smaller answers
        **_options_of(args),
    )
    print(summary.report(), file=sys.stderr)
    return summary.exit_code


def _run(args: argparse.Namespace) -> int:
    with PranetClient(args.url, api_key=args.api_key, timeout=args.timeout) as client:
        if args.command == "register":
            return _register(args, client)
        if args.command == "register-many":
            return _register_many(args, client)
        body = {"health": client.health, "ready": client.ready, "model": client.model}[args.command]()
        print(json.dumps(body, indent=2))
        return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return _run(args)
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
    except (PranetError, PointCloudIOError, CliError, OSError, ValueError) as e:
        message = " ".join(str(e).split()) or type(e).__name__
        print(f"error: {message}", file=sys.stderr)
        return 1
    except Exception as e:  # noqa: BLE001 - the CLI promises one line, never a traceback
        message = " ".join(str(e).split())
        print(f"error: unexpected {type(e).__name__}: {message}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
