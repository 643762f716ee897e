"""Paired differences between two `pranet-eval --json` files of the same setting (the test pairs), per method.

Pairs are matched by their hash (`pair_sha1`), so a run on the first N shapes (`--limit`) compares with the
full base run on those N. A few far-off pairs set each mean; the paired difference says whether a model moved
them or the rest.

    python experiments/eval_pairs.py results/eval-clean.json.gz /tmp/p16/eval-clean.json
"""

from __future__ import annotations

import argparse
import gzip
import json
from pathlib import Path

import numpy as np
from probe_pairs import paired  # the same paired mean and standard error as the validation probes


def records(path: Path) -> dict[str, dict[str, dict]]:
    """``{method: {pair_sha1: record}}``."""
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt") as f:
        doc = json.load(f)
    return {m: {r["pair_sha1"]: r for r in rs} for m, rs in doc["records"].items()}


def compare(method: str, new: dict[str, dict], base: dict[str, dict]) -> str:
    keys = [k for k in new if k in base]
    x = np.array([new[k]["rotation_deg"] for k in keys])
    y = np.array([base[k]["rotation_deg"] for k in keys])
    d = x - y
    mean, se = paired(x, y)
    sx = np.array([new[k]["success"] for k in keys], bool)
    sy = np.array([base[k]["success"] for k in keys], bool)
    worse, better = int((d > 5).sum()), int((d < -5).sum())
    return (
        f"{method:16s} {len(keys)} pairs: rotation mean {x.mean():.3f}° (base {y.mean():.3f}°), difference "
        f"{mean:+.3f} ± {se:.3f}°; median {np.median(x):.3f}° ({np.median(y):.3f}°); "
        f"pairs 5° worse / better: {worse} / {better}; success {sx.mean():.1%} ({sy.mean():.1%}), "
        f"made right {(sx & ~sy).sum()}, lost {(~sx & sy).sum()}"
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("base", type=Path)
    p.add_argument("new", type=Path)
    args = p.parse_args()
    base, new = records(args.base), records(args.new)
    for method in new:
        if method in base:
            print(compare(method, new[method], base[method]))


if __name__ == "__main__":
    main()
