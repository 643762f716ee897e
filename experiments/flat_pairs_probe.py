"""The flat shapes among ModelNet40's test pairs: which pairs have a planar target (``Resolution.planar``), and how
PRANet-v1, v2 and the service default register them, each pair and its randomness exactly as ``pranet-eval``
makes them. Backs docs/DESIGN.md, "Flat clouds".

    python experiments/flat_pairs_probe.py --setting noisy               # every planar pair of the setting
    python experiments/flat_pairs_probe.py --setting clean --pairs 517,561,1049
"""

from __future__ import annotations

import argparse

import numpy as np


def main() -> None:
    from pranet.core.metrics import evaluate_pair
    from pranet.core.resolution import measure_resolution
    from pranet.engine.engine import Engine
    from pranet.training.evaluate import load_test_shapes, pranet_runner
    from pranet.training.samples import SETTINGS, make_pair, pair_rng

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--setting", default="clean", choices=SETTINGS)
    ap.add_argument("--pairs", default="", help="comma-separated pair indices (default: every planar pair)")
    ap.add_argument("--seed", type=int, default=1234, help="pranet-eval's seed of the test pairs")
    ap.add_argument("--model", default=None)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()

    _, idx, shapes, _ = load_test_shapes(argparse.Namespace(data_dir=None, limit=None))

    def pair(i: int):  # pranet-eval's pair i
        return make_pair(shapes[i], args.setting, pair_rng(args.seed, args.setting, i), 60.0, 0.5, "isotropic")

    if args.pairs:
        chosen = [int(i) for i in args.pairs.split(",")]
    else:
        chosen = [i for i in range(len(shapes)) if measure_resolution(pair(i).source, pair(i).target).planar]
    runner = pranet_runner(Engine.load(args.model, threads=args.threads))
    print(f"{args.setting}: pairs {chosen}")
    print("pair | shape | planarity / flatness | method | rotation ° | translation | status")
    for i in chosen:
        p = pair(i)
        r = measure_resolution(p.source, p.target)
        rng = np.random.default_rng([args.seed, SETTINGS.index(args.setting), i, 1])  # pranet-eval's first runner
        try:
            outputs = runner.fn(p, rng)
        except ValueError as e:
            print(f"{i} | {idx[i]} | {r.planarity:.3f} / {r.flatness:.3f} | all | refused: {e}")
            continue
        for method, out in sorted(outputs.items()):
            m = evaluate_pair(p.source, p.target, p.clean_source, out.transform, p.T_gt)
            line = f"{m.rotation_deg:.3f} | {m.translation:.4f} | {out.extra.get('status')}"
            print(f"{i} | {idx[i]} | {r.planarity:.3f} / {r.flatness:.3f} | {method} | {line}")


if __name__ == "__main__":
    main()
