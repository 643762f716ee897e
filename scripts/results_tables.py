"""Merge pranet-eval JSON files of the same pairs into one paper-style table per setting.

The baselines and the PRANet rows can come from separate runs (the pairs are seeded by setting and
index, so every run sees the same pairs); this refuses to merge runs whose pairs differ.

    python scripts/results_tables.py --markdown results/eval-noisy.json.gz   (or a baselines run and a PRANet run)

``--card DIR`` also records the model's own figures (rotation error mean and median, success, per method and
setting) in ``DIR/card.json`` under ``evaluation``: the bounds of the model-quality test come from there.
"""

from __future__ import annotations

import argparse
import gzip
import json
from collections import defaultdict
from pathlib import Path

from pranet.training.evaluate import format_table

ORDER = ("pranet-v1", "pranet-v2", "pranet-adaptive", "icp", "fgr", "ransac")
LABELS = {
    "pranet-v1": "PRANet-v1",
    "pranet-v2": "PRANet-v2",
    "pranet-adaptive": "PRANet adaptive (ours)",
    "icp": "ICP",
    "fgr": "FGR+ICP",
    "ransac": "RANSAC+ICP",
}
PAPER_FOOTNOTED = {"fgr"}  # the paper's FGR ran without ICP and with mesh normals (RESULTS.md footnote)


def _cell(x: float | None) -> str:
    return "–" if x is None else f"{x:.4g}"


def markdown_table(summary: dict, paper: dict) -> str:
    """The RESULTS.md table: our means, median rotation, success, median ms; the paper's means beside."""
    cols = ["method", "rot (°)", "rot median", "trans", "L2", "MCD", "success", "median ms"]
    cols += ["paper rot", "paper trans", "paper L2", "paper MCD"]
    lines = ["| " + " | ".join(cols) + " |", "| " + " | ".join(["---"] * len(cols)) + " |"]
    for m, s in summary.items():
        p = paper.get(m) or {}
        star = "*" if m in PAPER_FOOTNOTED and p else ""
        ours = [s["rotation_deg"], s["rotation_deg_median"], s["translation"], s["l2"], s["mcd"]]
        theirs = [p.get(k) for k in ("rotation_deg", "translation", "l2", "mcd")]
        cells = [LABELS.get(m, m), *map(_cell, ours), f"{100 * s['success_rate']:.1f} %", f"{s['ms_median']:.1f}"]
        cells += [_cell(x) + (star if x is not None else "") for x in theirs]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("files", nargs="+", type=Path)
    p.add_argument("--markdown", action="store_true", help="print the RESULTS.md markdown tables")
    p.add_argument("--card", type=Path, help="model directory whose card.json gets the 'evaluation' figures")
    args = p.parse_args()
    evaluation: dict[str, dict] = {}
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
        print(markdown_table(summary, paper) if args.markdown else format_table(summary, paper))
        for m in ("pranet-v1", "pranet-v2", "pranet-adaptive", "icp"):
            if m in summary:
                s = summary[m]
                evaluation.setdefault(m, {})[setting] = {
                    "rotation_deg": s["rotation_deg"],
                    "rotation_deg_median": s["rotation_deg_median"],
                    "success_rate": s["success_rate"],
                    "pairs": n,
                    "seed": seed,
                }
    if args.card:
        card_path = args.card / "card.json"
        card = json.loads(card_path.read_text())
        card["evaluation"] = evaluation  # not part of the graphs' digests: card.json only
        card_path.write_text(json.dumps(card, indent=2) + "\n")


if __name__ == "__main__":
    main()
