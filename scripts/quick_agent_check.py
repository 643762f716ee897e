"""Quick look at a checkpoint: export it to a temp dir and run the agent on a few unseen test pairs.

Usage: python scripts/quick_agent_check.py runs/cpu/last.pt [--setting clean] [--limit 20]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from pranet.core.metrics import isotropic_errors
from pranet.core.pipeline import register
from pranet.model.export import card_from_checkpoint, export_model, load_checkpoint
from pranet.model.runtime import RewardModel
from pranet.service.icp import make_icp
from pranet.training.data import data_dir, load_modelnet40, test_indices
from pranet.training.samples import make_pair, pair_rng


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("checkpoint", type=Path)
    p.add_argument("--setting", default="clean")
    p.add_argument("--limit", type=int, default=20)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    net, ck = load_checkpoint(args.checkpoint)
    with tempfile.TemporaryDirectory() as tmp:
        export_model(net, Path(tmp), card_from_checkpoint(ck, "check", "0"))
        model = RewardModel.load(tmp, threads=args.threads)
    data = load_modelnet40(data_dir(), "test")
    idx = test_indices(data.labels)[: args.limit]
    icp = make_icp()
    rows = []
    for i, s in enumerate(idx):
        pair = make_pair(data.points[s], args.setting, pair_rng(0, args.setting, i))
        reg = register(pair.source, pair.target, model, np.random.default_rng(i), icp=icp)
        r0 = isotropic_errors(np.eye(4), pair.T_gt)
        r1 = isotropic_errors(reg.agent_transform, pair.T_gt)
        r2 = isotropic_errors(reg.transform, pair.T_gt)
        rows.append((*r0, *r1, *r2))
    a = np.array(rows)
    print(f"epoch {ck['epoch'] + 1} val {ck['val_loss']:.5f}  {args.setting} n={len(a)}")
    print(f"initial  rot {a[:, 0].mean():6.2f}  trans {a[:, 1].mean():.4f}")
    print(f"v1       rot {a[:, 2].mean():6.2f} (median {np.median(a[:, 2]):.2f})  trans {a[:, 3].mean():.4f}")
    print(
        f"v2       rot {a[:, 4].mean():6.2f} (median {np.median(a[:, 4]):.2f})  trans {a[:, 5].mean():.4f}  "
        f"success {np.mean((a[:, 4] < 1) & (a[:, 5] < 0.01)) * 100:.0f}%"
    )


if __name__ == "__main__":
    main()
