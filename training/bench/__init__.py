"""``pranet-bench``: CPU latency, accuracy and throughput of PRANet against Open3D and small_gicp, side by side.

One run, the same unseen-category ModelNet40 pairs for every method (``make_pair(shape, setting,
pair_rng(seed, setting, i), 60, 0.5)``, as ``pranet-eval`` builds them), methods interleaved pair by pair
(their order rotated per pair) so that a noisy machine affects all of them alike. It reports:

1. per setting and method: median and p95 latency (ms), success rate (rotation < 1° and translation
   < 0.01, ``core.metrics``), median errors. Methods: ``pranet-v1`` (agent only, in-process),
   ``pranet-v2`` (agent + ICP: ``Engine.register`` with ``PAPER_V2``),
   ``pranet-v2-http`` (the same through a real ``pranet-serve`` on a loopback port, base64 clouds,
   client-side latency: encoding, HTTP, JSON), ``icp``, ``fgr-icp``, ``ransac-icp``
   (``training.baselines``), ``ransac-pranet-icp`` (the same RANSAC, refined by the engine's ICP
   instead of point-to-point ICP: the peer with the service's refinement) and ``small-gicp``
   (``small_gicp.align``, GICP from the identity);
2. each method's median latency as a ratio to RANSAC+ICP's and to FGR+ICP's;
3. where a registration's time goes (``Registration.timing_ms``; HTTP/JSON overhead = client latency
   minus the server's own total);
4. the reward net's achieved GFLOP/s (MatMul/Gemm/Conv FLOPs of one ``score.onnx`` call, counted from
   an onnxruntime profile, over the measured time per call and per agent step) against this CPU's
   sgemm throughput (numpy float32 matmul and one onnxruntime MatMul, measured in this run);
5. per-step latency of onnxruntime session options (optimisation level, threads, spinning, memory
   arena/pattern, execution mode) and of the int8 graphs, measured interleaved;
6. int8: reward drift against fp32 along the fp32 agent's trajectories (max/mean |Δ|, agreement of the
   chosen action), latency and accuracy; early stop: latency saving and accuracy cost;
7. service throughput (registrations/s) with 1 and 2 uvicorn workers under concurrent clients.

Examples::

    pranet-bench                                   # 200 pairs per setting, everything (~20 min)
    pranet-bench --pairs 20 --throughput-seconds 10 --markdown docs/bench.md
    pranet-bench --pairs 5 --methods pranet-v1,pranet-v2,icp --throughput-seconds 0 --ort-calls 0

``pranet-bench scans [PAIRS.csv]`` is the real-scan benchmark: the service's default request beside classical
peers on scan pairs with a ground truth (``training.bench.scans``).
"""

from pranet.training.bench.catalog import METHODS
from pranet.training.bench.cli import main
from pranet.training.bench.flops import node_flops
from pranet.training.bench.methods import pranet_method, refined_by
from pranet.training.bench.ort import ORT_VARIANTS
from pranet.training.bench.records import as_float32, pair_seed
from pranet.training.bench.report import LABELS
from pranet.training.bench.tables import md_table, median

__all__ = [
    "LABELS",
    "METHODS",
    "ORT_VARIANTS",
    "as_float32",
    "main",
    "md_table",
    "median",
    "node_flops",
    "pair_seed",
    "pranet_method",
    "refined_by",
]
