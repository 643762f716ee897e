"""How well an analytic network's matching estimates the residual pose, by state size and setting.

On the validation shapes: states drawn up to 60°, 10° and 2° (translations 0.5, 0.1, 0.02); the median
rotation error of the estimate (degrees) and its translation error. Backs docs/DESIGN.md, "The agent".

    python experiments/estimate_probe.py runs/agent/last.pt --states 64
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

COMPONENTS = ((60.0, 0.5), (10.0, 0.1), (2.0, 0.02))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoints", nargs="+", type=Path)
    p.add_argument("--states", type=int, default=64)
    p.add_argument("--n-points", type=int, default=None, help="points per cloud (default: the network's)")
    args = p.parse_args()
    data = load_modelnet40(data_dir(None), "train")
    shapes = data.points[split_train_val(data.labels, 1234, 0.1).val][: args.states]
    for path in args.checkpoints:
        net, ck = load_checkpoint(path)
        cfg = TrainConfig.from_dict(ck["config"])
        if args.n_points:
            cfg = replace(cfg, net=replace(cfg.net, n_points=args.n_points))
        table = build_action_table(cfg.scales)
        for setting in ("clean", "noisy", "partial"):
            row = []
            for angle, trans in COMPONENTS:
                c = replace(cfg, sampling=replace(cfg.sampling, settings=((setting, 1.0),)))
                states = StateDistribution(((angle, trans, 1.0),), "isotropic", cfg.sampling.orientation_max_deg)
                ds = StateDataset(shapes, c, table, states, (777,))
                batch = [torch.stack(x) for x in zip(*[ds[i] for i in range(len(ds))], strict=True)]
                with torch.no_grad():
                    R_hat, t_hat, _, _ = net.pose_and_rewards(*batch[:4])
                R_res = R_hat.double().numpy() @ batch[5].double().numpy().transpose(0, 2, 1)
                rot = np.degrees(rotation_angle(R_res))
                tr = np.linalg.norm(t_hat.numpy() - batch[6].numpy(), axis=1)
                row.append(f"≤{angle:g}°: {np.median(rot):5.2f}° / {np.median(tr):.3f}")
            print(f"{str(path):32s} {setting:8s} " + "   ".join(row), flush=True)


if __name__ == "__main__":
    main()
