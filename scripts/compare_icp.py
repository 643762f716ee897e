"""v2 ICP variants from the same agent results (docs/DESIGN.md, "ICP of PRANet-v2").

    python scripts/compare_icp.py runs/cpu/best.pt 40     # checkpoint, pairs per setting (noisy, partial)

Single passes of point-to-point and point-to-plane ICP at 0.05 and 0.1 (unit frame), each from the agent's
estimate (the session-1 comparison; the stage lists of today's ICP: scripts/icp_select.py).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

from pranet.core.metrics import isotropic_errors
from pranet.core.pipeline import register
from pranet.model.export import card_from_checkpoint, export_model, load_checkpoint
from pranet.model.runtime import RewardModel
from pranet.service.icp import POINT_TO_PLANE, POINT_TO_POINT, make_icp
from pranet.training.data import data_dir, load_modelnet40, test_indices
from pranet.training.samples import make_pair, pair_rng


def main() -> None:
    net, ck = load_checkpoint(Path(sys.argv[1]))
    tmp = Path(tempfile.mkdtemp())
    export_model(net, tmp, card_from_checkpoint(ck, "compare", "0"))
    model = RewardModel.load(tmp, threads=1)
    data = load_modelnet40(data_dir(), "test")
    idx = test_indices(data.labels)[: int(sys.argv[2])]
    variants = {
        "point-to-point 0.05": make_icp(((POINT_TO_POINT, 0.05),)),
        "point-to-point 0.1": make_icp(((POINT_TO_POINT, 0.1),)),
        "point-to-plane 0.05": make_icp(((POINT_TO_PLANE, 0.05),)),
        "point-to-plane 0.1": make_icp(((POINT_TO_PLANE, 0.1),)),
    }
    for setting in ("noisy", "partial"):
        errors: dict[str, list[tuple[float, float]]] = {"agent only": [], **{k: [] for k in variants}}
        for i, s in enumerate(idx):
            pair = make_pair(data.points[s], setting, pair_rng(1234, setting, i))
            reg = register(pair.source, pair.target, model, np.random.default_rng(i))
            errors["agent only"].append(isotropic_errors(reg.transform, pair.T_gt))
            norm = reg.normalization
            src, tgt = norm.to_unit(pair.source), norm.to_unit(pair.target)
            for name, icp in variants.items():
                refined = icp(src, tgt, norm.transform_to_unit(reg.transform))
                errors[name].append(isotropic_errors(norm.transform_to_world(refined.transform), pair.T_gt))
        for name, e in errors.items():
            a = np.array(e)
            success = np.mean((a[:, 0] < 1) & (a[:, 1] < 0.01)) * 100
            print(
                f"{setting:8s} {name:20s} rot mean {a[:, 0].mean():7.3f} median {np.median(a[:, 0]):7.3f} "
                f"success {success:5.1f} %"
            )


if __name__ == "__main__":
    main()
