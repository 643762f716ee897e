"""The paper's agent (60 greedy steps, a network call per step) with another matching schedule in its fine phase.

The one-call estimate on partial pairs is about 10° off even from states within 2° of the truth, where ICP from the
same states is 0.6° off. Two reasons, both in how a call matches (docs/DESIGN.md, "Where the partial estimate goes
wrong"): the matching's coordinates are each cloud about its own centroid, so a partial pair starts its matching
0.1-0.2 from where the agent has put the source; and its first round leans on the features, which pull a
near-aligned partial pair off. A fine call here matches in the clouds' actual placement (both about the target's
centroid) and runs only the position-led rounds, tightened: ``--fine 1,2,2g4,2g16`` is round 1's and round 2's
trained (β, γ, α), then round 2's with γ × 4 and × 16 (a kernel 2× and 4× narrower). The coarse phase keeps the
trained call. Torch, on every point of the pair (as ``PAPER_AGENT_POINTS``), the validation pairs of
``agent_probe.py`` (same seeds); per pair the rotation error of the agent's result.

    python experiments/fine_matching_probe.py runs/p10-n358/best.pt --settings partial --pairs 150 \\
        --fine trained,1,2,2g4,2g16
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

import pranet.model.matching as matching
from pranet.core.actions import build_action_table
from pranet.core.agent import run_agent
from pranet.core.knn import knn_indices
from pranet.core.metrics import isotropic_errors
from pranet.model.export import load_checkpoint
from pranet.training.data import data_dir, load_modelnet40, split_train_val
from pranet.training.samples import make_pair, pair_rng


def parse_rounds(spec: str) -> list[tuple[int, float]]:
    """``"1,2,2g4"`` -> ``[(1, 1.0), (2, 1.0), (2, 4.0)]``: trained round index, γ multiplier."""
    rounds = []
    for item in spec.split("+"):
        idx, _, g = item.partition("g")
        rounds.append((int(idx), float(g) if g else 1.0))
    return rounds


def match(corr: matching.SinkhornCorrespondence, fx, fy, x, y, pooled, rounds: list[tuple[int, float]]):
    """``SinkhornCorrespondence.forward`` with a chosen list of rounds -> ``(R, r)``: ``y ≈ R x + r``."""
    B = x.shape[0]
    params = torch.nn.functional.softplus(corr.params(pooled)).view(B, corr.passes, 3) * corr.param_scales
    qx = torch.nn.functional.normalize(corr.q(fx), dim=-1)
    ky = torch.nn.functional.normalize(corr.k(fy), dim=-1)
    similarity = qx @ ky.transpose(1, 2)
    y_sq = (y * y).sum(-1).unsqueeze(1)
    R = torch.eye(3, dtype=x.dtype).expand(B, 3, 3)
    r = torch.zeros_like(x[:, 0])
    for i, g in rounds:
        beta, gamma, alpha = (params[:, i, j].view(B, 1, 1) for j in range(3))
        moved = x @ R.transpose(1, 2) + r.unsqueeze(1)
        d2 = (moved * moved).sum(-1, keepdim=True) - 2.0 * moved @ y.transpose(1, 2) + y_sq
        P = matching.sinkhorn_with_slack(beta * similarity - g * gamma * d2 - alpha, corr.iterations)
        R_i, r_i = matching.weighted_procrustes(P, moved, y)
        R, r = R_i @ R, (R_i @ r.unsqueeze(-1)).squeeze(-1) + r_i
    return R, r


def score_fn(net, target: np.ndarray, k: int, rounds: list[tuple[int, float]] | None):
    """``score_fn(source, target) -> rewards`` for ``run_agent``; ``rounds=None``: the trained call."""
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
            if rounds is None:
                return net.score(src_feat, c_s, tgt_feat, c_t, src_pts, tgt_pts)[0].numpy()
            src, tgt = src_feat, tgt_feat
            for block in net.blocks:
                src, tgt = block(src, tgt), block(tgt, src)
            pooled = torch.cat([net._pool(src), net._pool(tgt)], dim=-1)
            # Both clouds about the target's centroid: the matching starts where the agent has put the source.
            x, y = src_pts - c_t.unsqueeze(1), tgt_pts - c_t.unsqueeze(1)
            R, r = match(net.correspondence, src, tgt, x, y, pooled, rounds)
            # y - c_t = R (x - c_s) + R (c_s - c_t) + r: the translation still to add to the source centroid.
            t = r + (R @ (c_s - c_t).unsqueeze(-1)).squeeze(-1) - (c_s - c_t)
            return net.analytic(R, t)[0].numpy()

    return score


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint", type=Path)
    p.add_argument("--pairs", type=int, default=150)
    p.add_argument("--settings", default="partial")
    p.add_argument("--fine", default="trained,1+2+2g4+2g16", help="fine-phase schedules, comma-separated")
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
        for fine in args.fine.split(","):
            rounds = None if fine == "trained" else parse_rounds(fine)
            errors, t0 = [], time.perf_counter()
            for i in range(args.pairs):
                pair = make_pair(shapes[i % len(shapes)], setting, pair_rng(99, setting, i))
                coarse = run_agent(pair.source, pair.target, score_fn(net, pair.target, k, None), table, (20, 0))
                result = run_agent(
                    pair.source,
                    pair.target,
                    score_fn(net, pair.target, k, rounds),
                    table,
                    (0, 40),
                    initial_transform=coarse.transform,
                )
                errors.append(isotropic_errors(result.transform, pair.T_gt)[0])
            e = np.array(errors)
            out[f"{setting} {fine}"] = [float(v) for v in e]
            print(
                f"{setting:8s} fine={fine:22s} v1 mean {e.mean():6.2f}° median {np.median(e):6.2f}°"
                f"  < 1°: {np.mean(e < 1) * 100:5.1f} %  ({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )
            if args.json:
                args.json.write_text(json.dumps(out))


if __name__ == "__main__":
    main()
