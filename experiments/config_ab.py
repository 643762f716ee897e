"""Two service configurations side by side on real-scan pairs: per pair, each one's median milliseconds over
``--repeats`` runs (order alternating, every content cache emptied before each run, so each run prepares its
target as a new request does), right or wrong, status, winning candidate and confidence; then the totals. Backs
docs/DESIGN.md, "Doubtful candidates wait their turn".

    python experiments/config_ab.py PAIRS.csv --set defer_doubtful=False [--repeats 3] [--threads 1]

A is the service default; B is the default with the ``--set`` changes (RegistrationConfig fields, Python literals).
"""

import argparse
import ast
import gc
import statistics
import time

from pranet.client.io import read_point_cloud
from pranet.core.registration_config import SERVICE_DEFAULT
from pranet.engine.content_cache import LastByContent
from pranet.engine.engine import Engine
from pranet.training.bench.scan_pairs import is_right, pose_errors, read_pairs, thresholds_for


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("pairs_csv")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="B's change (repeatable)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--skip", default="lidar", help="skip pairs whose id contains this ('' = none)")
    return p.parse_args()


def empty_caches() -> None:
    """Every content cache (the ICP's and the polish's prepared targets): each run then pays what a new request
    on that target pays; without this the second configuration run on a pair found its target ready."""
    for obj in gc.get_objects():
        if isinstance(obj, LastByContent):
            obj._last.clear()


def main() -> None:
    args = parse_args()
    changes = {k: ast.literal_eval(v) for k, v in (s.split("=", 1) for s in args.set)}
    configs = {"A": SERVICE_DEFAULT, "B": SERVICE_DEFAULT.with_(**changes)}
    engine = Engine.load(threads=args.threads)
    engine.warm_up()
    medians = {"A": [], "B": []}
    right = {"A": 0, "B": 0}
    print(f"A: the service default; B: {changes}; {args.repeats} runs each, {args.threads} thread(s)")
    for i, pair in enumerate(read_pairs(args.pairs_csv)):
        if args.skip and args.skip in pair.id:
            continue
        src, tgt = read_point_cloud(pair.source), read_point_cloud(pair.target)
        ms, last = {"A": [], "B": []}, {}
        for r in range(args.repeats):
            for k in ("A", "B") if (r + i) % 2 == 0 else ("B", "A"):
                empty_caches()
                t0 = time.perf_counter()
                last[k] = engine.register(src, tgt, configs[k])
                ms[k].append(1e3 * (time.perf_counter() - t0))
        line = f"{pair.id[:36]:36s}"
        for k in "AB":
            reg = last[k]
            ok = is_right(*pose_errors(reg.T_target_source, pair.T_gt), thresholds_for(pair.kind))
            medians[k].append(statistics.median(ms[k]))
            right[k] += ok
            line += (
                f" | {k} {medians[k][-1]:6.0f} ms {'right' if ok else 'wrong'} {reg.confidence.status:9s} "
                f"{reg.candidate:12s} {reg.confidence.score:.3f}"
            )
        print(f"{line} | B/A {medians['B'][-1] / medians['A'][-1]:.2f}", flush=True)
    for k in "AB":
        print(
            f"{k}: right {right[k]}/{len(medians[k])}, median {statistics.median(medians[k]):.0f} ms, "
            f"sum {sum(medians[k]):.0f} ms"
        )


if __name__ == "__main__":
    main()
