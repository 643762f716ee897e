"""Where each cloud is centred before the network sees it: does a crop's own centroid cost the partial estimate?

Every network centres each cloud on its own centroid (``NetConfig.center_inputs``). Two crops of one shape have
centroids 0.1-0.2 apart, so at the true pose one surface point enters the two embeddings at positions that differ
by that much, and the matching's distance term (``||x̂_i - y_j||²``, first round at the identity) pulls the
same way. This probe keeps the trained weights and moves only the centre, for the features (``feat``) and for
the matching's coordinates (``geo``): ``own`` is each cloud's centroid (as trained), ``tgt`` the target's centroid
for both clouds. The one-call estimate of the residual pose on validation states up to 45°, 10° and 2°
(translations 0.5, 0.1, 0.02); per cell the median / mean rotation error (degrees), then the median / mean
translation error, as ``procrustes_probe.py`` reports them. With several checkpoints (``--variants own/own``
for the trained centring only) each later one also gets its paired rotation difference from the first, mean ±
standard error over the same states.

    python experiments/centering_probe.py runs/p10-n358/best.pt --states 128
    python experiments/centering_probe.py runs/p18-control/best.pt runs/p18-local/best.pt --variants own/own
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from pranet.core.actions import build_action_table
from pranet.core.se3 import rotation_angle
from pranet.model.export import load_checkpoint
from pranet.training.config import TrainConfig
from pranet.training.data import data_dir, load_modelnet40, split_train_val
from pranet.training.samples import StateDistribution
from pranet.training.train import StateDataset

COMPONENTS = ((45.0, 0.5), (10.0, 0.1), (2.0, 0.02))
VARIANTS = (("own", "own"), ("tgt", "own"), ("own", "tgt"), ("tgt", "tgt"))


def estimate(net, source, source_knn, target, target_knn, feat: str, geo: str):
    """The residual pose ``(R_err, t_err)`` about the source centroid, with the chosen centres."""
    c_s, c_t = source.mean(1), target.mean(1)
    f_centre = c_s if feat == "own" else c_t
    g_centre = c_s if geo == "own" else c_t
    src = net.embedding(source - f_centre.unsqueeze(1), source_knn)
    tgt = net.embedding(target - c_t.unsqueeze(1), target_knn)
    pair = net.pair_features(src, g_centre, tgt, c_t, source, target)
    R, r = pair[:, :9].reshape(-1, 3, 3), pair[:, 9:12]
    # y - c_t = R (x - g) + r = R (x - c_s) + R (c_s - g) + r: the translation about the source centroid.
    r_own = r + (R @ (c_s - g_centre).unsqueeze(-1)).squeeze(-1)
    return R, r_own - (c_s - c_t)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoints", type=Path, nargs="+")
    p.add_argument("--states", type=int, default=128)
    p.add_argument("--settings", default="noisy,partial")
    p.add_argument("--variants", default=",".join(f"{f}/{g}" for f, g in VARIANTS), help="feat/geo,...")
    args = p.parse_args()
    variants = [tuple(v.split("/")) for v in args.variants.split(",")]
    data = load_modelnet40(data_dir(None), "train")
    shapes = data.points[split_train_val(data.labels, 1234, 0.1).val][: args.states]
    nets = [load_checkpoint(path) for path in args.checkpoints]
    for net, _ in nets:
        net.eval()
    # The states come from the first checkpoint's config (settings, N), so every network sees the same ones.
    cfg = TrainConfig.from_dict(nets[0][1]["config"])
    table = build_action_table(cfg.scales)
    for setting in args.settings.split(","):
        c = replace(cfg, sampling=replace(cfg.sampling, settings=((setting, 1.0),)))
        batches = []
        for angle, trans in COMPONENTS:
            states = StateDistribution(((angle, trans, 1.0),), "isotropic", cfg.sampling.orientation_max_deg)
            ds = StateDataset(shapes, c, table, states, (777,))
            batches.append([torch.stack(x) for x in zip(*[ds[i] for i in range(len(ds))], strict=True)])
        first: list[np.ndarray] = []
        for k, ((net, _), path) in enumerate(zip(nets, args.checkpoints, strict=True)):
            for feat, geo in variants:
                cells = []
                for j, ((angle, _), batch) in enumerate(zip(COMPONENTS, batches, strict=True)):
                    with torch.no_grad():
                        R_hat, t_hat = estimate(net, *batch[:4], feat, geo)
                    R_res = R_hat.double().numpy() @ batch[5].double().numpy().transpose(0, 2, 1)
                    rot = np.degrees(rotation_angle(R_res))
                    tr = np.linalg.norm(t_hat.numpy() - batch[6].numpy(), axis=1)
                    cell = f"≤{angle:g}°: {np.median(rot):5.2f}/{np.mean(rot):5.2f}°"
                    cell += f" {np.median(tr):.3f}/{np.mean(tr):.3f}"
                    if k == 0:
                        first.append(rot)
                    elif len(variants) == 1:
                        d = rot - first[j]
                        cell += f" ({d.mean():+.2f} ± {d.std(ddof=1) / np.sqrt(len(d)):.2f}°)"
                    cells.append(cell)
                run = [path.parent.name] if len(nets) > 1 else []
                name = " ".join(run + ([f"feat={feat} geo={geo}"] if len(variants) > 1 else []))
                print(f"{setting:8s} {name:14s} " + "   ".join(cells), flush=True)


if __name__ == "__main__":
    main()
