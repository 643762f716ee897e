"""The ICP stages and the finish on ModelNet40 pairs, started from the true pose and from it turned: how many end
right (1° / 0.01). Per pair of pranet-bench's first N unseen-category pairs of a setting (its pairs and seeds):
the service's stages with least squares or Tukey's kernel at k spacings, and after the kernel's stages the
symmetric robust point-to-point finish (``core.robust_icp``) at k spacings. Backs docs/DESIGN.md, "A robust kernel
on sparse clouds" and "A finish for partial overlap".

    python experiments/partial_icp_probe.py --setting partial --pairs 100 --turns 20,40
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.spatial.transform import Rotation

from pranet.core.metrics import SUCCESS_ROTATION_DEG, SUCCESS_TRANSLATION, isotropic_errors
from pranet.core.registration_config import DEFAULT_ICP_STAGES, ICP_KERNEL
from pranet.core.registration_context import prepare
from pranet.core.robust_icp import symmetric_robust_icp
from pranet.engine.icp import make_icp
from pranet.training.bench.records import as_float32, pair_seed
from pranet.training.data import data_dir, load_modelnet40, test_indices
from pranet.training.samples import make_pair, pair_rng


def is_right(clouds, pair, T_unit: np.ndarray) -> bool:
    rot, trans = isotropic_errors(clouds.norm.transform_to_world(T_unit), pair.T_gt)
    return bool(rot < SUCCESS_ROTATION_DEG and trans < SUCCESS_TRANSLATION)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--setting", default="partial")
    p.add_argument("--pairs", type=int, default=100)
    p.add_argument("--turns", default="20,40", help="degrees the starts are turned off the truth (plus 0)")
    p.add_argument("--kernels", default="2,3", help="Tukey scales of the stages, in spacings")
    p.add_argument("--finishes", default="1,1.5,2", help="Tukey scales of the finish, in spacings")
    args = p.parse_args()
    turns = [0.0] + [float(t) for t in args.turns.split(",")]
    stages = {"least squares": make_icp(DEFAULT_ICP_STAGES)}
    for k in args.kernels.split(","):
        stages[f"Tukey {k} spacings"] = make_icp(DEFAULT_ICP_STAGES, kernel=float(k))
    finishes = [float(f) for f in args.finishes.split(",")]
    kernel_icp = make_icp(DEFAULT_ICP_STAGES, kernel=ICP_KERNEL)
    right: dict[str, list[int]] = {name: [0] * len(turns) for name in stages}
    right.update({f"kernel's stages + finish at {f}": [0] * len(turns) for f in finishes})
    data = load_modelnet40(data_dir(None), "test")
    rng = np.random.default_rng(0)
    for i, j in enumerate(test_indices(data.labels)[: args.pairs]):
        pair = as_float32(make_pair(data.points[j], args.setting, pair_rng(0, args.setting, i), 60.0, 0.5))
        c = prepare(pair.source, pair.target, 256, np.random.default_rng(pair_seed(0, args.setting, i)))
        truth = c.norm.transform_to_unit(pair.T_gt)

        for t, turn in enumerate(turns):
            axis = rng.normal(size=3)
            start = np.eye(4)
            start[:3, :3] = Rotation.from_rotvec(np.deg2rad(turn) * axis / np.linalg.norm(axis)).as_matrix()
            start[:3, 3] = rng.normal(size=3) * (0.03 if turn else 0.0)
            start = start @ truth
            for name, icp in stages.items():
                right[name][t] += is_right(c, pair, icp(c.src_unit, c.tgt_unit, start, c.resolution).transform)
            staged = kernel_icp(c.src_unit, c.tgt_unit, start, c.resolution).transform
            for f in finishes:
                scale = f * c.resolution.spacing
                finished = symmetric_robust_icp(c.src_index, c.tgt_index, staged, scale)
                right[f"kernel's stages + finish at {f}"][t] += is_right(c, pair, finished)
    turned = " / ".join(f"{t:g}°" for t in turns[1:])
    print(f"{args.setting}, {args.pairs} pairs: right from the truth / turned {turned}")
    for name, counts in right.items():
        print(f"  {name:36s} " + " / ".join(str(n) for n in counts))


if __name__ == "__main__":
    main()
