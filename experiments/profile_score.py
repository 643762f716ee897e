"""Where a ``score.onnx`` (or ``--graph score_fine.onnx``) call's time goes, by ONNX op, from an onnxruntime
profile (1 thread, 20 calls), after the median wall time of 40 unprofiled calls and the node count onnxruntime runs.

    python experiments/profile_score.py model/default --points 128
    python experiments/profile_score.py model/default --points 1024 --graph score_fine.onnx

Backs docs/DESIGN.md, "Global mode with the 2.0.0 network" (23 -> 13 ms per call: run it on an export of
``runs/agent/best.pt`` made with ``model/network.py`` of commit 4aabdec^ and of 4aabdec; the time moves
with the machine's load) and "Fewer nodes in the network call" (an export of ``runs/agent-2.1/best.pt`` made with
``model/matching.py`` of commit 7a85cd4^ and of 7a85cd4) and "Subnormal exponents" (the shipped model of
commit 45f5edf against 2.2.1: ``Exp``'s share).
"""

from __future__ import annotations

import argparse
import collections
import json
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

from pranet.core.knn import knn_indices


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model_dir", nargs="?", default="model/default")
    p.add_argument("--points", type=int, default=256, help="points per cloud (the service's agent sees 128)")
    p.add_argument("--graph", default="score.onnx", choices=("score.onnx", "score_fine.onnx"))
    args = p.parse_args()
    embed = ort.InferenceSession(f"{args.model_dir}/embed.onnx", providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    src = rng.normal(size=(1, args.points, 3)).astype(np.float32)
    tgt = rng.normal(size=(1, args.points, 3)).astype(np.float32)
    t_feat, t_cen = embed.run(None, {"points": tgt, "knn": knn_indices(tgt, 16)})
    feeds = {
        "points": src,
        "knn": knn_indices(src, 16),
        "target_points": tgt,
        "target_features": t_feat,
        "target_centroid": t_cen,
        # Graphs with the twin term (model 2.3.0) take it as an input; two random clouds have no twins.
        "twin": np.zeros((1, args.points, args.points), dtype=np.float32),
    }
    for profiled in (False, True):
        options = ort.SessionOptions()
        options.enable_profiling = profiled
        options.intra_op_num_threads = 1
        score = ort.InferenceSession(f"{args.model_dir}/{args.graph}", options, providers=["CPUExecutionProvider"])
        inputs = {i.name: feeds[i.name] for i in score.get_inputs()}
        calls = 20 if profiled else 40
        for _ in range(0 if profiled else 5):
            score.run(None, inputs)
        times = []
        for _ in range(calls):
            t0 = time.perf_counter()
            score.run(None, inputs)
            times.append(time.perf_counter() - t0)
        if not profiled:
            print(f"median {1e3 * np.median(times):.2f} ms per call unprofiled ({calls} calls, 1 thread)")
    by_op: collections.Counter = collections.Counter()
    nodes: collections.Counter = collections.Counter()
    profile = Path(score.end_profiling())
    with open(profile) as f:
        for e in json.load(f):
            if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
                by_op[e["args"].get("op_name", "")] += e["dur"]
                nodes[e["args"].get("op_name", "")] += 1
    profile.unlink()  # onnxruntime writes it into the working directory
    total = sum(by_op.values())
    print(f"{sum(nodes.values()) // calls} nodes run per call (after onnxruntime's graph optimisation); profiled:")
    for op, us in by_op.most_common(12):
        print(f"{us / calls / 1e3:7.2f} ms  {100 * us / total:5.1f} %  {nodes[op] // calls:4d}  {op}")
    print(f"total per call {total / calls / 1e3:.2f} ms (profiled)")


if __name__ == "__main__":
    main()
