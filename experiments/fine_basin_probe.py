"""The fine phase alone (40 steps) from a fixed offset of the truth, on test pairs, for several fine-phase calls.

Where the 40 fine steps of the paper's agent end when they start ``--deg`` degrees (about a random axis, at the
source's centroid) and ``--trans`` (a random direction) off the true pose: the basin and the precision of a
fine-phase call in one number. Torch, on every point of the pair; the schedules as ``fine_matching_probe.py``
(``trained`` for the trained call, else rounds in the clouds' actual placement, ``model.config.parse_rounds``).

    python experiments/fine_basin_probe.py runs/p10-n358/best.pt --setting partial --pairs 12 --deg 6 --trans 0.04 \\
        --fine trained,1+2+2g4+2g16,2g4+2g4+2g16+2g16
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from fine_matching_probe import score_fn
from scipy.spatial.transform import Rotation

from pranet.core.actions import build_action_table
from pranet.core.agent import run_agent
from pranet.core.metrics import isotropic_errors
from pranet.core.se3 import make_transform
from pranet.model.config import parse_rounds
from pranet.model.export import load_checkpoint
from pranet.training.data import data_dir, load_modelnet40, test_indices
from pranet.training.samples import make_pair, pair_rng


def offsets(n: int, deg: float, trans: float, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` rotations of ``deg`` about random axes and translations of length ``trans`` in random directions."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        axis, direction = rng.normal(size=3), rng.normal(size=3)
        R = Rotation.from_rotvec(np.deg2rad(deg) * axis / np.linalg.norm(axis)).as_matrix()
        out.append((R, trans * direction / np.linalg.norm(direction)))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint", type=Path)
    p.add_argument("--setting", default="partial")
    p.add_argument("--pairs", type=int, default=12)
    p.add_argument("--deg", type=float, default=6.0)
    p.add_argument("--trans", type=float, default=0.04)
    p.add_argument("--fine", default="trained,1+2+2g4+2g16")
    p.add_argument("--seed", type=int, default=5)
    args = p.parse_args()
    torch.set_num_threads(1)
    net, ck = load_checkpoint(args.checkpoint)
    table = build_action_table([tuple(s) for s in ck["config"]["scales"]])
    data = load_modelnet40(data_dir(None), "test")
    shapes = data.points[test_indices(data.labels)]
    pairs = [
        make_pair(shapes[i], args.setting, pair_rng(1234, args.setting, i), 60.0, 0.5, "isotropic")
        for i in range(args.pairs)
    ]
    for fine in args.fine.split(","):
        rounds = None if fine == "trained" else parse_rounds(fine)
        errors = []
        for pair, (R, t) in zip(pairs, offsets(len(pairs), args.deg, args.trans, args.seed), strict=True):
            at_truth = pair.source @ pair.T_gt[:3, :3].T + pair.T_gt[:3, 3]
            c = at_truth.mean(axis=0)
            start = make_transform(R, c + t - R @ c)  # turned about the centroid, then moved
            moved = at_truth @ start[:3, :3].T + start[:3, 3]
            result = run_agent(moved, pair.target, score_fn(net, pair.target, net.cfg.k, rounds), table, (0, 40))
            errors.append(isotropic_errors(result.transform @ start, np.eye(4)))
        e = np.array(errors)
        print(
            f"{args.setting:8s} from {args.deg:g}° / {args.trans:g}  fine={fine:24s}"
            f" rotation mean {e[:, 0].mean():5.2f}° median {np.median(e[:, 0]):5.2f}°"
            f"  translation mean {e[:, 1].mean():.4f}",
            flush=True,
        )


if __name__ == "__main__":
    main()
