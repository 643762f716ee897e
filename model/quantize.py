"""int8 variants of a model directory: dynamic quantization of its graphs with onnxruntime (no torch).

``quantize_model_dir(dir)`` writes ``embed.int8.onnx``, ``score.int8.onnx`` (and ``head.int8.onnx``,
``score_fine.int8.onnx`` when the model has ``head.onnx``, ``score_fine.onnx``) beside the fp32 graphs and lists
them in ``card.json`` (``files``, with their sha256, checked at load like the fp32 ones), together with a
``quantization`` entry naming the fp32 graphs they were made from, so that a stale int8 file (the fp32 graphs
re-exported since) is refused. ``RewardModel.load(dir, precision="int8")`` loads them; the service does with
``PRANET_PRECISION=int8``. ``pranet-export --int8`` calls this.

Dynamic quantization: the weights of MatMul/Gemm become int8 (per output channel), activations are
quantized per tensor at run time. MatMuls of two activations (attention scores, attention @ values)
stay fp32 (``MatMulConstBOnly``), which keeps the drift of the rewards small; so do the MLP heads
(``FP32_PREFIXES``: 0.4 of 265 MFLOP per step, and most of the drift when quantized), so ``head.int8.onnx``
computes what ``head.onnx`` does.

``reduce_range`` (the default) keeps the weights to 7 bits. On x86-64 CPUs without VNNI (AVX2 only),
onnxruntime's u8×s8 kernel adds pairs of products in saturating int16 (``VPMADDUBSW``); with full-range
weights the shipped model's rewards then drifted by up to 0.066 from fp32 (on rewards of order 0.3),
against 0.002 on an AVX-512 VNNI machine. With 7-bit weights the sums cannot saturate: the drift on the
AVX2 machine fell to 0.005-0.011 (``tests/model/test_quantize.py`` measures it on whatever CPU runs it).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

from pranet.engine.runtime import fine_file, graph_files, head_file, sha256_file

FP32_GRAPHS = graph_files("fp32")
INT8_GRAPHS = graph_files("int8")
HEAD_GRAPHS = (head_file("fp32"), head_file("int8"))  # (fp32, int8), when the model has a head graph
FINE_GRAPHS = (fine_file("fp32"), fine_file("int8"))  # (fp32, int8), when the model has a fine-phase graph
OP_TYPES = ("MatMul", "Gemm")
# The MLP heads stay fp32: their input concatenates pooled features with the small centroid offset and the
# correspondence rotation, and one per-tensor activation scale for all of them cost the trained model up to 0.04
# of reward drift (on rewards of order 0.18) for 0.4 of its 265 MFLOP per step. Node-name prefixes of the export.
# The analytic reward layer (its constants are the action table) and the matching's sharpness network stay fp32
# as well: quantizing them would perturb the rewards themselves, for no measurable time. So do the matching's own
# constant products (``/correspondence/MatMul_*``: Horn's matrix of H and the rotation of q qᵀ, exact linear maps
# whose entries are 0, ±1 and ±2, not learned weights); its learned projections (``/correspondence/q``, ``/k``) do not.
# The cross-attention block stays fp32 too: with 2.2.0's weights its int8 products drifted the rewards by up to 0.031
# (of rewards up to 0.56) on the drift test's clouds, 0.016 with it in fp32 (8 seeds; docs/DESIGN.md, "Model 2.2.0").
FP32_PREFIXES = (
    "/blocks",
    "/shared",
    "/rotation_head",
    "/translation_head",
    "/analytic",
    "/correspondence/params",
    "/correspondence/MatMul",
)


def quantize_graph(src: Path, dst: Path, per_channel: bool = True, reduce_range: bool = True) -> None:
    """Dynamic int8 quantization of one ONNX graph (weights QInt8, activations quantized at run time)."""
    import onnx
    from onnxruntime.quantization import QuantType, quantize_dynamic
    from onnxruntime.quantization.shape_inference import quant_pre_process

    with tempfile.TemporaryDirectory() as tmp:
        prepared = Path(tmp) / "prepared.onnx"
        # onnxruntime's symbolic shape pass cannot follow the twin input's broadcast over the rows (core.twins), and
        # when it fails it leaves its temporary files in the working directory: such graphs take ONNX's own pass.
        symbolic = "twin" not in {i.name for i in onnx.load(str(src), load_external_data=False).graph.input}
        try:  # shape inference + graph cleanup, as onnxruntime recommends before quantizing
            quant_pre_process(str(src), str(prepared), skip_symbolic_shape=not symbolic)
        except Exception:  # pre-processing is an optimisation; quantize the graph as it is if it fails
            prepared = src
        graph = onnx.load(str(prepared), load_external_data=False).graph
        keep_fp32 = [n.name for n in graph.node if n.op_type in OP_TYPES and n.name.startswith(FP32_PREFIXES)]
        keep_fp32 += [f"{name}_MatMul" for name in keep_fp32]  # quantize_dynamic first turns Gemm into MatMul + Add
        quantize_dynamic(
            str(prepared),
            str(dst),
            nodes_to_exclude=keep_fp32,
            op_types_to_quantize=list(OP_TYPES),
            per_channel=per_channel,
            reduce_range=reduce_range,
            weight_type=QuantType.QInt8,
            extra_options={"MatMulConstBOnly": True},
        )
    # Keep the model's metadata (card fields) on the int8 graph too.
    meta = {p.key: p.value for p in onnx.load(str(src), load_external_data=False).metadata_props}
    model = onnx.load(str(dst))
    del model.metadata_props[:]
    for key, value in {**meta, "precision": "int8"}.items():
        model.metadata_props.add(key=key, value=value)
    onnx.save(model, str(dst))


def quantize_model_dir(model_dir: str | Path, per_channel: bool = True, reduce_range: bool = True) -> dict[str, Any]:
    """Write the int8 graphs into ``model_dir`` and list them in its card; returns the updated card."""
    import onnxruntime

    from pranet.engine.runtime import read_card

    model_dir = Path(model_dir)
    card_path = model_dir / "card.json"
    card = read_card(model_dir, verify=True)  # quantize only verified fp32 graphs
    pairs = list(zip(FP32_GRAPHS, INT8_GRAPHS, strict=True))
    pairs += [optional for optional in (HEAD_GRAPHS, FINE_GRAPHS) if optional[0] in card.get("files", {})]
    for fp32, int8 in pairs:
        quantize_graph(model_dir / fp32, model_dir / int8, per_channel=per_channel, reduce_range=reduce_range)
    int8_names = INT8_GRAPHS + HEAD_GRAPHS[1:] + FINE_GRAPHS[1:]
    files = {k: v for k, v in card.get("files", {}).items() if k not in int8_names}
    files.update({int8: sha256_file(model_dir / int8) for _, int8 in pairs})
    card["files"] = files
    card["quantization"] = {
        "method": "onnxruntime.quantization.quantize_dynamic",
        "weight_type": "QInt8",
        "per_channel": per_channel,
        "reduce_range": reduce_range,
        "op_types": list(OP_TYPES),
        "matmul_const_b_only": True,
        "fp32_nodes": list(FP32_PREFIXES),
        "onnxruntime": onnxruntime.__version__,
        "from": {fp32: files.get(fp32) for fp32, _ in pairs},  # the fp32 graphs the int8 ones were made from
    }
    card_path.write_text(json.dumps(card, indent=2) + "\n")
    return card
