"""Paired differences between `agent_probe.py --json` files: each model against a base, pair by pair.

The probe runs every model on the same pairs, so the difference of two means has the standard error of the
per-pair differences, far smaller than either mean's own (a few far-off pairs set a mean; most pairs move together).

    python experiments/probe_pairs.py runs/p14-partial/probe-2.2.0.json runs/p16-polish/probe-*.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def load(path: Path) -> dict[str, dict]:
    """``{setting: record}`` of one probe file (a list of records, one per model and setting)."""
    return {r["setting"]: r for r in json.loads(path.read_text())}


def paired(new: np.ndarray, base: np.ndarray) -> tuple[float, float]:
    """Mean and standard error of ``new - base``."""
    d = new - base
    return float(d.mean()), float(d.std(ddof=1) / np.sqrt(len(d)))


def report(name: str, new: dict, base: dict) -> list[str]:
    lines = [f"{name}, {new['setting']}, {len(new['per_pair']['v1'])} pairs"]
    for key in ("v1", "v2"):
        x, y = (np.asarray(r["per_pair"][key], float) for r in (new, base))
        mean, se = paired(x, y)
        lines.append(
            f"  {key}: mean {x.mean():7.3f}° (base {y.mean():7.3f}°), median {np.median(x):6.3f}° "
            f"({np.median(y):6.3f}°), difference {mean:+.3f} ± {se:.3f}°; over 30°: {(x > 30).sum()} "
            f"({(y > 30).sum()}), over 60°: {(x > 60).sum()} ({(y > 60).sum()})"
        )
    x, y = (np.asarray(r["per_pair"]["service_ok"], bool) for r in (new, base))
    lines.append(f"  service default right: {x.sum()} ({y.sum()}); made right {(x & ~y).sum()}, lost {(~x & y).sum()}")
    return lines


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("base", type=Path, help="the base model's probe file")
    p.add_argument("new", type=Path, nargs="+", help="probe files of the models to compare")
    args = p.parse_args()
    base = load(args.base)
    for path in args.new:
        for setting, record in load(path).items():
            if setting not in base:
                print(f"{path}: no {setting} pairs in the base file")
                continue
            print("\n".join(report(str(path), record, base[setting])))


if __name__ == "__main__":
    main()
