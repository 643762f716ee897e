"""Where a ``score.onnx`` call's time goes, by ONNX op, from an onnxruntime profile (1 thread, 20 calls).

    python experiments/profile_score.py model/default

Backs docs/DESIGN.md, "Global mode with the 2.0.0 network" (23 -> 13 ms per call: run it on an export of
``runs/agent/best.pt`` made with ``model/network.py`` of commit 4aabdec^ and of 4aabdec; the time moves
with the machine's load).
"""

from __future__ import annotations

import collections
import json
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort

from pranet.core.knn import knn_indices


def main() -> None:
    model_dir = sys.argv[1] if len(sys.argv) > 1 else "model/default"
    options = ort.SessionOptions()
    options.enable_profiling = True
    options.intra_op_num_threads = 1
    embed = ort.InferenceSession(f"{model_dir}/embed.onnx", providers=["CPUExecutionProvider"])
    score = ort.InferenceSession(f"{model_dir}/score.onnx", options, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    src = rng.normal(size=(1, 256, 3)).astype(np.float32)
    tgt = rng.normal(size=(1, 256, 3)).astype(np.float32)
    t_feat, t_cen = embed.run(None, {"points": tgt, "knn": knn_indices(tgt, 16)})
    feeds = {
        "points": src,
        "knn": knn_indices(src, 16),
        "target_points": tgt,
        "target_features": t_feat,
        "target_centroid": t_cen,
    }
    names = [i.name for i in score.get_inputs()]
    calls = 20
    for _ in range(calls):
        score.run(None, {n: feeds[n] for n in names})
    by_op: collections.Counter = collections.Counter()
    profile = Path(score.end_profiling())
    with open(profile) as f:
        for e in json.load(f):
            if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
                by_op[e["args"].get("op_name", "")] += e["dur"]
    profile.unlink()  # onnxruntime writes it into the working directory
    total = sum(by_op.values())
    for op, us in by_op.most_common(12):
        print(f"{us / calls / 1e3:7.2f} ms  {100 * us / total:5.1f} %  {op}")
    print(f"total per call {total / calls / 1e3:.2f} ms")


if __name__ == "__main__":
    main()
