"""Merge pranet-eval JSON files of the same pairs into one paper-style table per setting.

The baselines and the PRANet rows can come from separate runs (the pairs are seeded by setting and
index, so every run sees the same pairs); this refuses to merge runs whose pairs differ.

    python scripts/results_tables.py results/baselines-noisy.json.gz results/pranet-noisy.json.gz
"""

from __future__ import annotations

import argparse
import gzip
import json
from collections import defaultdict
from pathlib import Path

from pranet.training.evaluate import format_table

ORDER = ("pranet-v1", "pranet-v2", "icp", "fgr", "ransac")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("files", nargs="+", type=Path)
    args = p.parse_args()
    by_setting: dict[str, list[dict]] = defaultdict(list)
    for f in args.files:
        doc = json.loads(gzip.decompress(f.read_bytes()) if f.suffix == ".gz" else f.read_text())
        by_setting[doc["config"]["setting"]].append(doc)
    for setting, docs in by_setting.items():
        keys = {
            (d["config"]["seed"], d["config"]["n_pairs"], d["config"]["max_angle"], d["config"]["rotation"])
            for d in docs
        }
        if len(keys) != 1:
            raise SystemExit(f"{setting}: runs on different pairs {sorted(keys)}; not merging")
        summary, paper = {}, {}
        for d in docs:
            summary.update(d["summary"])
            paper.update(d["paper"])
        summary = {m: summary[m] for m in ORDER if m in summary}
        seed, n, angle, rotation = keys.pop()
        print(f"\n{setting}: {n} pairs, seed {seed}, {rotation} rotation <= {angle}°, translation <= 0.5")
        print(format_table(summary, paper))


if __name__ == "__main__":
    main()
