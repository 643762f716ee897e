"""The paper's agent (60 greedy steps, a network call per step) with another matching schedule in its fine phase.

The one-call estimate on partial pairs is about 10° off even from states within 2° of the truth, where ICP from the
same states is 0.6° off. Two reasons, both in how a call matches (docs/DESIGN.md, "Where the partial estimate goes
wrong"): the matching's coordinates are each cloud about its own centroid, so a partial pair starts its matching
0.1-0.2 from where the agent has put the source; and its first round leans on the features, which pull a
near-aligned partial pair off. A fine call here matches in the clouds' actual placement (both about the target's
centroid) and runs only the position-led rounds, tightened: ``--fine 1+2+2g4+2g16`` (``model.config.FINE_ROUNDS``,
what ``score_fine.onnx`` runs) is round 1's and round 2's trained (β, γ, α), then round 2's with γ × 4 and × 16 (a
kernel 2× and 4× narrower); several schedules are comma-separated. ``--coarse`` takes the same syntax for the 20
coarse steps (default: the trained call). Torch, on every point of the pair (as ``PAPER_AGENT_POINTS``), the
validation pairs of ``agent_probe.py`` (same seeds); per pair the rotation error of the agent's result.

    python experiments/fine_matching_probe.py runs/p10-n358/best.pt --settings partial --pairs 150 \\
        --fine trained,1+2+2g4+2g16
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from pranet.core.actions import build_action_table
from pranet.core.agent import run_agent
from pranet.core.knn import knn_indices
from pranet.core.metrics import isotropic_errors
from pranet.model.config import MatchingRound, parse_rounds
from pranet.model.export import load_checkpoint
from pranet.training.data import data_dir, load_modelnet40, split_train_val
from pranet.training.samples import make_pair, pair_rng


def score_fn(net, target: np.ndarray, k: int, rounds: tuple[MatchingRound, ...] | None):
    """``score_fn(source, target) -> rewards`` for ``run_agent``; ``rounds=None``: the trained call, else a call
    on ``rounds`` in the clouds' actual placement (``RewardNet.pair_features``)."""
    tgt_pts = torch.from_numpy(target).float()[None]
    tgt_knn = torch.from_numpy(knn_indices(target, k))[None]
    with torch.no_grad():
        tgt_feat, c_t = net.embed(tgt_pts, tgt_knn)
    src_knn: list[torch.Tensor] = []  # the source's graph does not change with its pose

    def score(source: np.ndarray, _target: np.ndarray) -> np.ndarray:
        src_pts = torch.from_numpy(np.asarray(source, dtype=np.float32))[None]
        if not src_knn:
            src_knn.append(torch.from_numpy(knn_indices(source, k))[None])
        with torch.no_grad():
            src_feat, c_s = net.embed(src_pts, src_knn[0])
            pair = net.pair_features(src_feat, c_s, tgt_feat, c_t, src_pts, tgt_pts, rounds)
            return net.head(pair, c_s - c_t)[0].numpy()

    return score


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint", type=Path)
    p.add_argument("--pairs", type=int, default=150)
    p.add_argument("--settings", default="partial")
    p.add_argument("--fine", default="trained,1+2+2g4+2g16", help="fine-phase schedules, comma-separated")
    p.add_argument("--coarse", default="trained", help="coarse-phase schedules, comma-separated (same syntax)")
    p.add_argument("--json", type=Path)
    args = p.parse_args()
    torch.set_num_threads(1)
    net, ck = load_checkpoint(args.checkpoint)
    net.eval()
    table = build_action_table([tuple(s) for s in ck["config"]["scales"]])
    k = net.cfg.k
    data = load_modelnet40(data_dir(None), "train")
    shapes = data.points[split_train_val(data.labels, 1234, 0.1).val]
    out = {}
    for setting in args.settings.split(","):
        pairs = [make_pair(shapes[i % len(shapes)], setting, pair_rng(99, setting, i)) for i in range(args.pairs)]
        for coarse_spec in args.coarse.split(","):
            coarse_rounds = None if coarse_spec == "trained" else parse_rounds(coarse_spec)
            # The coarse phase's end, once per coarse schedule, is every fine schedule's start.
            starts = [
                run_agent(pair.source, pair.target, score_fn(net, pair.target, k, coarse_rounds), table, (20, 0))
                for pair in pairs
            ]
            for fine in args.fine.split(","):
                rounds = None if fine == "trained" else parse_rounds(fine)
                t0 = time.perf_counter()
                errors = []
                for pair, coarse in zip(pairs, starts, strict=True):
                    fine_score = score_fn(net, pair.target, k, rounds)
                    result = run_agent(
                        pair.source, pair.target, fine_score, table, (0, 40), initial_transform=coarse.transform
                    )
                    errors.append(isotropic_errors(result.transform, pair.T_gt)[0])
                e = np.array(errors)
                out[f"{setting} {coarse_spec} {fine}"] = [float(v) for v in e]
                print(
                    f"{setting:8s} coarse={coarse_spec:14s} fine={fine:24s} v1 mean {e.mean():6.2f}°"
                    f" median {np.median(e):6.2f}°  < 1°: {np.mean(e < 1) * 100:5.1f} %"
                    f"  ({time.perf_counter() - t0:.0f} s fine)",
                    flush=True,
                )
                if args.json:
                    args.json.write_text(json.dumps(out))


if __name__ == "__main__":
    main()
