"""Robust variants of the matching's weighted Procrustes: does the pose solve, or the matching, miss on partial pairs?

Each variant replaces ``pranet.model.matching.weighted_procrustes`` (every matching pass calls it) and the
one-call estimate of the residual pose is measured on validation states, as ``estimate_probe.py`` does: states up
to 45°, 10° and 2° (translations 0.5, 0.1, 0.02); per cell the median / mean rotation error (degrees), then the
median / mean translation error. Variants reweight the soft assignment's rows after a first solve:

- ``trim70``: refit on the 70 % of rows with the smallest residuals ``||R x_i + r - ŷ_i||``;
- ``cauchy<σ>``: two iteratively reweighted refits, row weights ``1 / (1 + e_i² / σ²)``;
- ``oracle``: no reweighting, but the rows of source points with no true counterpart in the target
  (``training.train.overlap_labels``) dropped: what a perfect overlap mask would buy.

Backs docs/DESIGN.md, "Robust weights for the matching's pose solve".

    python experiments/procrustes_probe.py runs/p10-n358/best.pt --states 128
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

import pranet.model.matching as matching
from pranet.core.actions import build_action_table
from pranet.core.se3 import rotation_angle
from pranet.model.export import load_checkpoint
from pranet.training.config import TrainConfig
from pranet.training.data import data_dir, load_modelnet40, split_train_val
from pranet.training.samples import StateDistribution
from pranet.training.train import StateDataset, overlap_labels

COMPONENTS = ((45.0, 0.5), (10.0, 0.1), (2.0, 0.02))
BASE = matching.weighted_procrustes


def residuals(P: torch.Tensor, x: torch.Tensor, y: torch.Tensor, R: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """``||R x_i + r - ŷ_i||`` per row, ``ŷ_i`` the row's soft match."""
    y_hat = (P @ y) / (P.sum(-1, keepdim=True) + 1e-9)
    moved = x @ R.transpose(1, 2) + r.unsqueeze(1)
    return (moved - y_hat).norm(dim=-1)  # (B, N)


def trimmed(keep: float) -> Callable:
    def solve(P, x, y):
        R, r = BASE(P, x, y)
        e = residuals(P, x, y, R, r)
        cut = torch.quantile(e, keep, dim=1, keepdim=True)
        return BASE(P * (e <= cut).unsqueeze(-1).to(P.dtype), x, y)

    return solve


def cauchy(sigma: float, refits: int = 2) -> Callable:
    def solve(P, x, y):
        R, r = BASE(P, x, y)
        for _ in range(refits):
            e = residuals(P, x, y, R, r)
            R, r = BASE(P * (1.0 / (1.0 + (e / sigma) ** 2)).unsqueeze(-1), x, y)
        return R, r

    return solve


# The current batch's true overlap of each source point, for ``oracle`` (set by ``estimate_errors``).
ORACLE_ROWS: list[torch.Tensor] = []


def oracle(P, x, y):
    return BASE(P * ORACLE_ROWS[0].unsqueeze(-1), x, y)


VARIANTS: dict[str, Callable] = {
    "base": BASE,
    "trim70": trimmed(0.7),
    "cauchy0.05": cauchy(0.05),
    "oracle": oracle,
}


def estimate_errors(net, cfg: TrainConfig, shapes: np.ndarray, setting: str, angle: float, trans: float):
    table = build_action_table(cfg.scales)
    c = replace(cfg, sampling=replace(cfg.sampling, settings=((setting, 1.0),)))
    states = StateDistribution(((angle, trans, 1.0),), "isotropic", cfg.sampling.orientation_max_deg)
    ds = StateDataset(shapes, c, table, states, (777,))
    batch = [torch.stack(x) for x in zip(*[ds[i] for i in range(len(ds))], strict=True)]
    ORACLE_ROWS[:] = [overlap_labels(batch[0], batch[2], batch[5], batch[6])[0]]
    with torch.no_grad():
        R_hat, t_hat, _, _ = net.pose_and_rewards(*batch[:4])
    R_res = R_hat.double().numpy() @ batch[5].double().numpy().transpose(0, 2, 1)
    rot = np.degrees(rotation_angle(R_res))
    tr = np.linalg.norm(t_hat.numpy() - batch[6].numpy(), axis=1)
    return rot, tr


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint", type=Path)
    p.add_argument("--states", type=int, default=128)
    p.add_argument("--settings", default="noisy,partial")
    args = p.parse_args()
    data = load_modelnet40(data_dir(None), "train")
    shapes = data.points[split_train_val(data.labels, 1234, 0.1).val][: args.states]
    net, ck = load_checkpoint(args.checkpoint)
    cfg = TrainConfig.from_dict(ck["config"])
    for setting in args.settings.split(","):
        for name, solve in VARIANTS.items():
            matching.weighted_procrustes = solve
            cells = []
            for angle, trans in COMPONENTS:
                rot, tr = estimate_errors(net, cfg, shapes, setting, angle, trans)
                cells.append(
                    f"≤{angle:g}°: {np.median(rot):5.2f}/{np.mean(rot):5.2f}° {np.median(tr):.3f}/{np.mean(tr):.3f}"
                )
            print(f"{setting:8s} {name:11s} " + "   ".join(cells), flush=True)
    matching.weighted_procrustes = BASE


if __name__ == "__main__":
    main()
