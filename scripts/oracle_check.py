"""The MDP's ceiling: the greedy agent driven by the exact rewards (a perfect reward network).

    python scripts/oracle_check.py [--problems 20]

Random anisotropic clouds, isotropic rotations up to 60°, translations up to 0.5; prints the mean and
worst isotropic errors after the default 20 + 40 steps.
"""

from __future__ import annotations

import argparse

import numpy as np

from pranet.core.actions import build_action_table
from pranet.core.agent import oracle_score_fn, run_agent
from pranet.core.metrics import isotropic_errors
from pranet.core.sampling import sample_isotropic_rotations, sample_translations
from pranet.core.se3 import apply_transform, make_transform


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--problems", type=int, default=20)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    table = build_action_table()
    errors = []
    for _ in range(args.problems):
        src = rng.standard_normal((300, 3)) * [0.5, 0.3, 0.2]
        T = make_transform(sample_isotropic_rotations(rng, np.deg2rad(60), 1)[0], sample_translations(rng, 0.5, 1)[0])
        res = run_agent(src, apply_transform(T, src), oracle_score_fn(T, src, table), table)
        errors.append(isotropic_errors(res.transform, T))
    e = np.array(errors)
    print(
        f"{args.problems} problems: rotation mean {e[:, 0].mean():.3f}° worst {e[:, 0].max():.3f}°, "
        f"translation mean {e[:, 1].mean():.4f} worst {e[:, 1].max():.4f}"
    )


if __name__ == "__main__":
    main()
