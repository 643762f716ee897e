"""Two service configurations side by side on real-scan pairs: per pair, each one's median milliseconds over
``--repeats`` runs (order alternating, every content cache emptied before each run, so each run prepares its
target as a new request does), right or wrong, status, winning candidate and confidence; then the totals. With
``--modelnet N``: on pranet-bench's first N unseen-category ModelNet40 pairs per setting instead (its pairs and
seeds), success by the benchmark's thresholds and the median milliseconds. Backs docs/DESIGN.md, "Doubtful
candidates wait their turn" and "An exit check halfway through the coarse phase".

    python experiments/config_ab.py PAIRS.csv --set defer_doubtful=False [--repeats 3] [--threads 1]
    python experiments/config_ab.py --modelnet 150 --set "exit_checks=(20,40)"
    python experiments/config_ab.py PAIRS.csv --constant-b icp.DENSE_TOLERANCE=1e-6 --repeats 2
    python experiments/config_ab.py PAIRS.csv --constant-b icp.TARGET_VOXEL_SPACINGS=4.0
    python experiments/config_ab.py --modelnet 30 --base paper-v1 --model-a /tmp/old-model

``--model-a`` / ``--model-b``: model directories (default: the shipped one), so that two exports of one checkpoint
can be timed side by side; ``--base``: the configuration both start from (the service default, or the paper's v1 or
v2).

``--constant-b``: a constant of a ``pranet.engine`` module (``MODULE.NAME=VALUE``, a Python literal) set to another
value while B warms up and registers, and restored after. B has an engine of its own (the same model), so constants
read when its ICP functions are made (``icp.DENSE_TOLERANCE``: docs/DESIGN.md, "ICP tolerance on dense clouds") count
as well as those read during a registration.

A is the base configuration; B is the base with the ``--set`` changes (RegistrationConfig fields, Python literals).
"""

import argparse
import ast
import gc
import statistics
import time

from pranet.client.io import read_point_cloud
from pranet.core.registration_config import PAPER_V1, PAPER_V2, SERVICE_DEFAULT
from pranet.engine.content_cache import LastByContent
from pranet.engine.engine import Engine
from pranet.training.bench.scan_pairs import is_right, pose_errors, read_pairs, thresholds_for

BASES = {"service": SERVICE_DEFAULT, "paper-v1": PAPER_V1, "paper-v2": PAPER_V2}


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("pairs_csv", nargs="?")
    p.add_argument("--modelnet", type=int, metavar="N", help="ModelNet40 pairs per setting instead of scan pairs")
    p.add_argument("--settings", default="clean,noisy,partial")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="B's change (repeatable)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--constant-b", action="append", default=[], metavar="MODULE.NAME=VALUE", help="B's engine constant")
    p.add_argument("--skip", default="lidar", help="skip pairs whose id contains this ('' = none)")
    p.add_argument("--base", choices=sorted(BASES), default="service", help="the configuration A and B start from")
    p.add_argument("--model-a", default=None, help="A's model directory (default: the shipped model)")
    p.add_argument("--model-b", default=None, help="B's model directory (default: the shipped model)")
    return p.parse_args()


def empty_caches() -> None:
    """Every content cache (the ICP's and the polish's prepared targets): each run then pays what a new request
    on that target pays; without this the second configuration run on a pair found its target ready."""
    for obj in gc.get_objects():
        if isinstance(obj, LastByContent):
            obj._last.clear()


def modelnet(args: argparse.Namespace, engines: dict, configs: dict) -> None:
    """Both configurations on each ModelNet40 pair, interleaved: success and median milliseconds per setting."""
    import numpy as np

    from pranet.core.metrics import SUCCESS_ROTATION_DEG, SUCCESS_TRANSLATION, isotropic_errors
    from pranet.training.bench.records import as_float32, pair_seed
    from pranet.training.data import data_dir, load_modelnet40, test_indices
    from pranet.training.samples import make_pair, pair_rng

    data = load_modelnet40(data_dir(None), "test")
    shapes = test_indices(data.labels)[: args.modelnet]
    for setting in args.settings.split(","):
        ok, ms = {"A": 0, "B": 0}, {"A": [], "B": []}
        for i, j in enumerate(shapes):
            pair = as_float32(make_pair(data.points[j], setting, pair_rng(0, setting, i), 60.0, 0.5))
            seed = pair_seed(0, setting, i)
            for k in ("A", "B") if i % 2 == 0 else ("B", "A"):
                t0 = time.perf_counter()
                reg = engines[k].register(pair.source, pair.target, configs[k], np.random.default_rng(seed), seed=seed)
                ms[k].append(1e3 * (time.perf_counter() - t0))
                rot, trans = isotropic_errors(reg.T_target_source, pair.T_gt)
                ok[k] += bool(rot < SUCCESS_ROTATION_DEG and trans < SUCCESS_TRANSLATION)
        print(
            f"{setting:8s} "
            + " | ".join(f"{k}: {ok[k]}/{len(shapes)} right, median {statistics.median(ms[k]):.1f} ms" for k in "AB")
            + f" | B/A {statistics.median(ms['B']) / statistics.median(ms['A']):.2f}",
            flush=True,
        )


class PatchedEngine:
    """An engine whose ``warm_up`` and ``register`` run with some ``pranet.engine`` module constants changed."""

    def __init__(self, engine: Engine, constants: dict[tuple[str, str], object]) -> None:
        self.engine, self.constants = engine, constants

    def _call(self, method: str, *args, **kwargs):
        import importlib

        kept = {}
        for (module, name), value in self.constants.items():
            m = importlib.import_module(f"pranet.engine.{module}")
            kept[(m, name)] = getattr(m, name)
            setattr(m, name, value)
        try:
            return getattr(self.engine, method)(*args, **kwargs)
        finally:
            for (m, name), value in kept.items():
                setattr(m, name, value)

    def warm_up(self, *args, **kwargs):
        return self._call("warm_up", *args, **kwargs)

    def register(self, *args, **kwargs):
        return self._call("register", *args, **kwargs)


def parse_constants(items: list[str]) -> dict[tuple[str, str], object]:
    out = {}
    for item in items:
        path, value = item.split("=", 1)
        module, name = path.rsplit(".", 1)
        out[(module, name)] = ast.literal_eval(value)
    return out


def main() -> None:
    args = parse_args()
    changes = {k: ast.literal_eval(v) for k, v in (s.split("=", 1) for s in args.set)}
    base = BASES[args.base]
    configs = {"A": base, "B": base.with_(**changes)}
    engine = Engine.load(args.model_a, threads=args.threads)
    engine_b = engine if args.model_b == args.model_a else Engine.load(args.model_b, threads=args.threads)
    constants = parse_constants(args.constant_b)
    engines = {"A": engine, "B": PatchedEngine(Engine(engine_b.scorer), constants) if constants else engine_b}
    for e in engines.values():
        e.warm_up()
    b_engine = "".join(f", {m}.{n}={v!r}" for (m, n), v in constants.items())
    models = {k: engines[k].scorer.info() if hasattr(engines[k], "scorer") else {} for k in "AB"}
    print("models: " + ", ".join(f"{k} {m.get('version')} {str(m.get('sha256'))[:12]}" for k, m in models.items()))
    if args.modelnet:
        print(f"A: {args.base}; B: {changes}{b_engine}; {args.threads} thread(s)")
        modelnet(args, engines, configs)
        return
    medians = {"A": [], "B": []}
    right = {"A": 0, "B": 0}
    print(f"A: {args.base}; B: {changes}{b_engine}; {args.repeats} runs each, {args.threads} thread(s)")
    for i, pair in enumerate(read_pairs(args.pairs_csv)):
        if args.skip and args.skip in pair.id:
            continue
        src, tgt = read_point_cloud(pair.source), read_point_cloud(pair.target)
        ms, last = {"A": [], "B": []}, {}
        for r in range(args.repeats):
            for k in ("A", "B") if (r + i) % 2 == 0 else ("B", "A"):
                empty_caches()
                t0 = time.perf_counter()
                last[k] = engines[k].register(src, tgt, configs[k])
                ms[k].append(1e3 * (time.perf_counter() - t0))
        line = f"{pair.id[:36]:36s}"
        for k in "AB":
            reg = last[k]
            errors = pose_errors(reg.T_target_source, pair.T_gt)
            ok = is_right(*errors, thresholds_for(pair.kind))
            medians[k].append(statistics.median(ms[k]))
            right[k] += ok
            line += (
                f" | {k} {medians[k][-1]:6.0f} ms {'right' if ok else 'wrong'} {errors[0]:.3f}° {errors[1]:.2e} "
                f"{reg.confidence.status:9s} "
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
