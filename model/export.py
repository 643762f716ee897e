"""``pranet-export``: a training checkpoint -> the ONNX model directory the service loads.

The directory holds three graphs, so that the target embedding stays separable and is computed once
per registration:

- ``embed.onnx``: ``points (B, N, 3) float32, knn (B, N, k) int64 -> features (B, N, D), centroid (B, 3)``
- ``score.onnx``: ``points, knn, target_points, target_features (B, M, D), target_centroid (B, 3)
  -> rewards (B, A), pair_features (B, P)``
- ``head.onnx``: ``pair_features (B, P), offset (B, 3) -> rewards (B, A)``, the MLP heads alone. With
  centred inputs (the ``cpu`` preset) a translation action leaves ``pair_features`` unchanged, so the
  runtime re-scores a translated source with this graph instead of ``score.onnx``.

- ``score_fine.onnx`` (Sinkhorn networks with the rounds it names): ``score.onnx``'s inputs and outputs, the
  fine phase's call, whose matching runs ``FINE_ROUNDS`` with both clouds about the target's centroid
  (``RewardNet.fine_call``); the card's ``fine_matching`` says so. Its pair features change with a translation;
  it also returns ``similarity (B, N, M)`` and ``match_params (B, passes, 3)``, which do not.
- ``match_fine.onnx``: ``points, target_points, target_centroid, similarity, match_params -> rewards``, the fine
  call's matching rounds alone (``MatchGraph``), which re-score a translated source from the last fine call's
  ``similarity`` and ``match_params`` (networks without an overlap head; the card's ``fine_matching.match_graph``).

and ``card.json``: preset, N, k, the action table (scales, names, fingerprint), the schedule, the
network config, the training summary and the sha256 of both graphs (checked at load). The same
metadata is stored in each graph's ``metadata_props``.

``--int8`` also writes dynamically quantized ``*.int8.onnx`` graphs (listed in the
card with their sha256; ``pranet.model.quantize``). Without a checkpoint, ``pranet-export --int8 --out
DIR`` adds them to the existing model directory ``DIR``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import torch

from pranet.core.actions import build_action_table
from pranet.core.twins import TWIN_K, TWIN_SIGMA, TWIN_WEIGHT
from pranet.engine.runtime import FINE_GRAPH, FINE_MATCH_GRAPH, graph_files, head_file, sha256_file
from pranet.model.config import FINE_ROUNDS, MatchingRound, NetConfig, format_rounds, parse_rounds
from pranet.model.network import EmbedGraph, FineScoreGraph, HeadGraph, MatchGraph, RewardNet, ScoreGraph

OPSET = 17
FP32_GRAPHS = (*graph_files("fp32"), head_file("fp32"))


def load_checkpoint(path: Path, match_passes: int | None = None) -> tuple[RewardNet, dict[str, Any]]:
    """The network of a ``pranet-train`` checkpoint, in eval mode, and the checkpoint. ``match_passes``: rounds of
    matching at inference (``NetConfig.inference_passes``; recorded in the returned checkpoint's config, so the
    card says what the exported graph runs)."""
    ck = torch.load(path, map_location="cpu", weights_only=False)
    cfg = ck["config"]
    if match_passes is not None:
        cfg["net"] = {**cfg["net"], "inference_passes": int(match_passes)}
    table = build_action_table(cfg["scales"])
    net = RewardNet(NetConfig.from_dict(cfg["net"]), table)
    net.load_state_dict(ck["model"])
    net.eval()
    return net, ck


def _set_metadata(path: Path, meta: dict[str, str]) -> None:
    import onnx

    m = onnx.load(str(path))
    del m.metadata_props[:]
    for k, v in meta.items():
        m.metadata_props.add(key=k, value=v)
    onnx.save(m, str(path))


def export_model(
    net: RewardNet,
    out: Path,
    card: dict[str, Any],
    fine_rounds: tuple[MatchingRound, ...] = FINE_ROUNDS,
    twins: bool = False,
) -> dict[str, Any]:
    """Write ``embed.onnx``, ``score.onnx``, ``head.onnx``, the fine phase's graphs (``export_fine_graphs``) and
    ``card.json`` into ``out``; returns the card. ``fine_rounds``: the fine graphs' matching rounds. ``twins``
    (Sinkhorn networks): the score graphs take ``core.twins``' term as a sixth input, ``twin``, and the card's
    ``twin_matching`` gives the runtime its settings."""
    twins = twins and net.cfg.correspondence and net.cfg.matching == "sinkhorn"
    out.mkdir(parents=True, exist_ok=True)
    # Made from the previous graphs, if any.
    for stale in [*out.glob("*.int8.onnx"), out / FINE_GRAPH, out / FINE_MATCH_GRAPH]:
        stale.unlink(missing_ok=True)
    cfg = net.cfg
    N, k = cfg.n_points, cfg.k
    # The graphs are traced in eval mode (inference rounds of matching, no dropout). The wrappers are made in eval
    # mode too: torch.onnx.export puts a module back in the mode it found it in, and a new module is in training
    # mode, which left ``net`` training after the export.
    pts = torch.randn(1, N, 3)
    knn = torch.randint(0, N, (1, N, k), dtype=torch.int64)
    with torch.no_grad():
        feats, cen = net.embed(pts, knn)
        pair = net.pair_features(feats, cen, feats, cen, pts, pts)
    axes = {"points": {0: "batch", 1: "n"}, "knn": {0: "batch", 1: "n"}}
    score_axes = {
        **axes,
        "target_points": {0: "batch", 1: "m"},
        "target_features": {0: "batch", 1: "m"},
        "target_centroid": {0: "batch"},
        "rewards": {0: "batch"},
        "pair_features": {0: "batch"},
    }
    torch.onnx.export(
        EmbedGraph(net).eval(),
        (pts, knn),
        str(out / "embed.onnx"),
        input_names=["points", "knn"],
        output_names=["features", "centroid"],
        dynamic_axes={**axes, "features": {0: "batch", 1: "n"}, "centroid": {0: "batch"}},
        opset_version=OPSET,
        dynamo=False,
    )
    example: tuple[torch.Tensor, ...] = (pts, knn, pts, feats, cen)
    inputs = ["points", "knn", "target_points", "target_features", "target_centroid"]
    if twins:
        # One (N, M) term per registration, broadcast over the rows (the starts) of a batched call.
        example, inputs = (*example, torch.zeros(1, N, N)), [*inputs, "twin"]
        score_axes["twin"] = {0: "twin_rows", 1: "n", 2: "m"}
        card = {**card, "twin_matching": {"input": "twin", "k": TWIN_K, "sigma": TWIN_SIGMA, "weight": TWIN_WEIGHT}}
    torch.onnx.export(
        ScoreGraph(net).eval(),
        example,
        str(out / "score.onnx"),
        input_names=inputs,
        output_names=["rewards", "pair_features"],
        dynamic_axes=score_axes,
        opset_version=OPSET,
        dynamo=False,
    )
    fine_graphs = export_fine_graphs(net, out, example, score_axes, fine_rounds)
    torch.onnx.export(
        HeadGraph(net).eval(),
        (pair, cen - cen),
        str(out / "head.onnx"),
        input_names=["pair_features", "offset"],
        output_names=["rewards"],
        dynamic_axes={"pair_features": {0: "batch"}, "offset": {0: "batch"}, "rewards": {0: "batch"}},
        opset_version=OPSET,
        dynamo=False,
    )
    meta = {k: json.dumps(v) for k, v in card.items() if k != "files"}
    for name in FP32_GRAPHS:
        _set_metadata(out / name, meta)
    graphs = FP32_GRAPHS
    if fine_graphs:
        # Added after the other graphs are stamped, so that a model exported before the fine call keeps their bytes.
        entry = {"graph": FINE_GRAPH, "rounds": format_rounds(fine_rounds)}
        match = {"match_graph": FINE_MATCH_GRAPH} if FINE_MATCH_GRAPH in fine_graphs else {}
        card = {**card, "fine_matching": {**entry, **match}}
        for name in fine_graphs:
            _set_metadata(out / name, {k: json.dumps(v) for k, v in card.items() if k != "files"})
        graphs = (*FP32_GRAPHS, *fine_graphs)
    card = {**card, "files": {name: sha256_file(out / name) for name in graphs}}
    (out / "card.json").write_text(json.dumps(card, indent=2) + "\n")
    return card


def export_fine_graphs(
    net: RewardNet,
    out: Path,
    example: tuple[torch.Tensor, ...],
    score_axes: dict[str, dict[int, str]],
    fine_rounds: tuple[MatchingRound, ...],
) -> tuple[str, ...]:
    """Write the fine phase's graphs (``has_fine_call``): ``score_fine.onnx`` and, without an overlap head (whose
    prior the match-only graph would have to carry too), ``match_fine.onnx``. ``example``: ``score.onnx``'s inputs.
    Returns the file names written."""
    if not has_fine_call(net.cfg, fine_rounds):
        return ()
    match_only = not net.cfg.overlap_head
    cached = {"similarity": {0: "batch", 1: "n", 2: "m"}, "match_params": {0: "batch"}} if match_only else {}
    torch.onnx.export(
        (FineScoreGraph(net, fine_rounds) if match_only else ScoreGraph(net, fine_rounds)).eval(),
        example,
        str(out / FINE_GRAPH),
        input_names=["points", "knn", "target_points", "target_features", "target_centroid", "twin"][: len(example)],
        output_names=["rewards", "pair_features", *cached],
        dynamic_axes={**score_axes, **cached},
        opset_version=OPSET,
        dynamo=False,
    )
    if not match_only:
        return (FINE_GRAPH,)
    pts, _, target, feats, cen = example[:5]
    with torch.no_grad():
        _, similarity, params = net.fine_call(feats, cen, feats, cen, pts, target, fine_rounds)
    torch.onnx.export(
        MatchGraph(net, fine_rounds).eval(),
        (pts, target, cen, similarity, params),
        str(out / FINE_MATCH_GRAPH),
        input_names=["points", "target_points", "target_centroid", "similarity", "match_params"],
        output_names=["rewards"],
        dynamic_axes={
            "points": {0: "batch", 1: "n"},
            "target_points": {0: "batch", 1: "m"},
            "target_centroid": {0: "batch"},
            **cached,
            "rewards": {0: "batch"},
        },
        opset_version=OPSET,
        dynamo=False,
    )
    return FINE_GRAPH, FINE_MATCH_GRAPH


def has_fine_call(cfg: NetConfig, fine_rounds: tuple[MatchingRound, ...] = FINE_ROUNDS) -> bool:
    """Whether the network can make the fine phase's call: Sinkhorn matching with every round ``fine_rounds`` names,
    and the analytic reward layer (whose rewards follow from the pose alone, wherever the matching ran)."""
    return (
        cfg.correspondence
        and cfg.matching == "sinkhorn"
        and cfg.reward_head == "analytic"
        and max(i for i, _ in fine_rounds) < cfg.match_passes
    )


def card_from_checkpoint(ck: dict[str, Any], name: str, version: str) -> dict[str, Any]:
    cfg = ck["config"]
    table = build_action_table(cfg["scales"])
    return {
        "name": name,
        "version": version,
        "preset": cfg["preset"],
        "n_points": cfg["net"]["n_points"],
        "k": cfg["net"]["k"],
        "actions": {
            "scales": [list(s) for s in table.scales],
            "names": list(table.names),
            "fingerprint": table.fingerprint,
        },
        "schedule": list(cfg["schedule"]),
        "net": cfg["net"],
        "training": {
            "epochs_completed": ck["epoch"] + 1,
            "epochs_planned": cfg["optim"]["epochs"],
            "wall_s": round(ck["wall_s"], 1),
            "val_loss": ck["val_loss"],
            "best_val_loss": ck["best_val"],
            "data_sha256": ck.get("data_sha256"),
            "seed": cfg["seed"],
        },
        "config": cfg,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="pranet-export", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("checkpoint", type=Path, nargs="?", help="a .pt file written by pranet-train")
    p.add_argument("--out", type=Path, required=True, help="model directory to write")
    p.add_argument("--name", default="pranet-cpu")
    p.add_argument("--version", default="0.1.0")
    p.add_argument(
        "--int8",
        action="store_true",
        help="also write int8 graphs (dynamic quantization); without a checkpoint: add them to --out",
    )
    p.add_argument(
        "--match-passes",
        type=int,
        default=None,
        help="rounds of Sinkhorn matching in the exported graph (default: as trained); rounds beyond the trained "
        "ones reuse the last round's parameters",
    )
    p.add_argument(
        "--fine-rounds",
        type=parse_rounds,
        default=FINE_ROUNDS,
        help=f"the fine-phase graph's matching rounds: trained round indices, gN for γ × N (default "
        f"{format_rounds(FINE_ROUNDS)})",
    )
    p.add_argument(
        "--twins",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the score graphs take core.twins' term (a point's twin in the other cloud, where the clouds share "
        "their points); --no-twins: the graphs as before it",
    )
    args = p.parse_args(argv)
    if args.checkpoint is None and not args.int8:
        p.error("a checkpoint is required (or --int8 to quantize the existing model directory --out)")
    if args.checkpoint is not None:
        net, ck = load_checkpoint(args.checkpoint, args.match_passes)
        card = card_from_checkpoint(ck, args.name, args.version)
        # Provenance: which checkpoint (path as given, relative to the repository root when run from it).
        card["checkpoint"] = {"path": args.checkpoint.as_posix(), "sha256": sha256_file(args.checkpoint)}
        card = export_model(net, args.out, card, args.fine_rounds, twins=args.twins)
    if args.int8:
        from pranet.model.quantize import quantize_model_dir

        card = quantize_model_dir(args.out)
    print(json.dumps({"out": str(args.out), "files": card["files"], "training": card.get("training")}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
