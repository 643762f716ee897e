"""What the polish does to the winner's confidence, right answers against wrong ones: per pair of each CSV, the
service default's winner, right or wrong, and its score before and after the polish (the polish run on every
winner, ``converged`` or not, as before this round). Backs docs/DESIGN.md, "The polish".

    python experiments/unseen_pairs.py /tmp/unseen
    python experiments/polish_status_probe.py ../shared/data/scans/pairs.csv /tmp/unseen/pairs.csv
"""

from __future__ import annotations

import sys
from dataclasses import replace

from pranet.client.io import read_point_cloud
from pranet.core import pipeline
from pranet.core.registration_config import SERVICE_DEFAULT
from pranet.engine.engine import Engine
from pranet.training.bench.scan_pairs import is_right, pose_errors, read_pairs, thresholds_for

scores: list[tuple[float, float]] = []


def polish_every_winner(ctx) -> None:
    """The polish as it was: run on any winner, kept unless it costs the winner its status and its score."""
    c, best = ctx.clouds, ctx.best
    T = ctx.polish(c.src_unit, c.tgt_unit, best.T_unit, c.resolution)
    after = best.confidence.score
    if T is not None:
        confidence = ctx.evaluate(T)
        after = confidence.score
        if confidence.status == "converged" or confidence.score >= best.confidence.score:
            ctx.best = replace(best, confidence=confidence, T_unit=T)
    scores.append((best.confidence.score, after))


def main() -> None:
    pipeline.polish = polish_every_winner
    engine = Engine.load(threads=1)
    for path in sys.argv[1:]:
        for pair in read_pairs(path):
            scores.clear()
            reg = engine.register(read_point_cloud(pair.source), read_point_cloud(pair.target), SERVICE_DEFAULT)
            right = is_right(*pose_errors(reg.T_target_source, pair.T_gt), thresholds_for(pair.kind))
            before, after = scores[0] if scores else (float("nan"), float("nan"))
            print(
                f"{pair.id:34s} {'right' if right else 'wrong'} {reg.candidate:12s} "
                f"before {before:.3f} after {after:.3f} ({after - before:+.3f})",
                flush=True,
            )


if __name__ == "__main__":
    main()
