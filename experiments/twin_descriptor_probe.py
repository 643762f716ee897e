"""Would a pose-blind local descriptor let the paper's agent tell a symmetric shape's turned copies apart?

On the clean setting every source point has an exact twin in the target (the same points, moved), with the same
distances to its neighbours; a turned copy of a vase has none. The probe adds ``λ · S`` (``core.twins``, through
``RewardNet.pair_features(twin=)``) to the matching's feature similarity, with ``S_ij = exp(-|d_i - d_j|² / (2 (σ
s)²))``, ``d`` the sorted distances of a point to its ``k`` nearest neighbours in its own cloud and ``s`` the median
neighbour distance: 1 for a twin, about 0 for anything else, and about 0 everywhere on independent samples (noisy,
partial),
so that it cannot pull those off. No weights change. Torch, the paper's protocol (20 coarse steps on the trained
call, 40 fine steps on ``FINE_ROUNDS``, every point), on the test pairs ``pranet-eval`` generates: those a base
``--json`` file says ended more than 10° off, then the first others up to ``--pairs``.

    python experiments/twin_descriptor_probe.py runs/p10-n358/best.pt results/eval-clean-fine.json.gz \\
        --setting clean --pairs 100 --lambdas 0,1
"""

from __future__ import annotations

import argparse
import gzip
import json
import time
from pathlib import Path

import numpy as np
import torch

from pranet.core.actions import build_action_table
from pranet.core.agent import run_agent
from pranet.core.knn import knn_indices
from pranet.core.metrics import isotropic_errors
from pranet.core.twins import twin_similarity
from pranet.model.config import FINE_ROUNDS
from pranet.model.export import load_checkpoint
from pranet.training.data import data_dir, load_modelnet40, test_indices
from pranet.training.samples import make_pair, pair_rng


def score_fn(net, target: np.ndarray, k: int, rounds, term: torch.Tensor | None):
    tgt_pts = torch.from_numpy(target).float()[None]
    with torch.no_grad():
        tgt_feat, c_t = net.embed(tgt_pts, torch.from_numpy(knn_indices(target, k))[None])
    src_knn: list[torch.Tensor] = []

    def score(source: np.ndarray, _target: np.ndarray) -> np.ndarray:
        src_pts = torch.from_numpy(np.asarray(source, dtype=np.float32))[None]
        if not src_knn:
            src_knn.append(torch.from_numpy(knn_indices(source, k))[None])
        with torch.no_grad():
            src_feat, c_s = net.embed(src_pts, src_knn[0])
            pair = net.pair_features(src_feat, c_s, tgt_feat, c_t, src_pts, tgt_pts, rounds, term)
            return net.head(pair, c_s - c_t)[0].numpy()

    return score


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint", type=Path)
    p.add_argument("base", type=Path, help="a pranet-eval --json file of the same setting (picks the far-off pairs)")
    p.add_argument("--setting", default="clean")
    p.add_argument("--pairs", type=int, default=100)
    p.add_argument("--lambdas", default="0,1")
    p.add_argument("--k", type=int, default=8, help="neighbours in the descriptor")
    p.add_argument("--sigma", type=float, default=0.05, help="kernel width, in median neighbour distances")
    p.add_argument("--others-only", action="store_true", help="leave out the far-off pairs")
    p.add_argument("--json", type=Path)
    args = p.parse_args()
    torch.set_num_threads(1)
    net, ck = load_checkpoint(args.checkpoint)
    net.eval()
    table = build_action_table([tuple(s) for s in ck["config"]["scales"]])
    fine_rounds = FINE_ROUNDS
    with gzip.open(args.base, "rt") as f:
        base = json.load(f)["records"]["pranet-v1"]
    far = [r["pair"] for r in base if r["rotation_deg"] > 10]
    others = [r["pair"] for r in base if r["rotation_deg"] <= 10]
    head = [] if args.others_only else far
    chosen = head + others[: max(0, args.pairs - len(head))]
    data = load_modelnet40(data_dir(None), "test")
    idx = test_indices(data.labels)
    out: dict[str, list[float]] = {"pair": chosen, "far": [i in far for i in chosen]}
    for lam in [float(x) for x in args.lambdas.split(",")]:
        t0, errors = time.perf_counter(), []
        for i in chosen:
            pair = make_pair(data.points[idx[i]], args.setting, pair_rng(1234, args.setting, i), 60.0, 0.5)
            term = None
            if lam:  # core.twins on the clouds' own kNN graphs, the runtime's term
                src_knn, tgt_knn = knn_indices(pair.source, net.cfg.k), knn_indices(pair.target, net.cfg.k)
                S = twin_similarity(pair.source, src_knn, pair.target, tgt_knn, args.k, args.sigma, lam)
                term = torch.from_numpy(S)[None]
            trained = score_fn(net, pair.target, net.cfg.k, None, term)
            coarse = run_agent(pair.source, pair.target, trained, table, (20, 0))
            fine = score_fn(net, pair.target, net.cfg.k, fine_rounds, term)
            result = run_agent(pair.source, pair.target, fine, table, (0, 40), initial_transform=coarse.transform)
            errors.append(isotropic_errors(result.transform, pair.T_gt)[0])
        e, f = np.array(errors), np.array(out["far"])
        out[f"lambda={lam:g}"] = [float(v) for v in e]
        far_mean = e[f].mean() if f.any() else float("nan")
        others_mean = e[~f].mean() if (~f).any() else float("nan")
        print(
            f"{args.setting} λ={lam:g}: far ({f.sum()}) mean {far_mean:.2f}°, others ({(~f).sum()}) mean "
            f"{others_mean:.3f}°, all {e.mean():.2f}° median {np.median(e):.3f}°  ({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
        if args.json:
            args.json.write_text(json.dumps(out))


if __name__ == "__main__":
    main()
