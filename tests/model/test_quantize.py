"""int8 graphs (dynamic quantization): written by ``pranet-export --int8``, listed and checked in the card,
loaded with ``precision="int8"``, and close to the fp32 rewards."""

import json
import shutil

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

from pranet.core.preprocess import fit_normalization, resample  # noqa: E402
from pranet.engine.runtime import ModelLoadError, RewardModel, default_model_dir, read_card  # noqa: E402
from pranet.model.quantize import INT8_GRAPHS, quantize_model_dir  # noqa: E402


@pytest.fixture(scope="module")
def int8_dir(tmp_path_factory):
    """A copy of the shipped model with its int8 graphs added (through the pranet-export CLI when torch is here)."""
    out = tmp_path_factory.mktemp("int8") / "model"
    shutil.copytree(default_model_dir(), out)
    try:
        from pranet.model.export import main as export_main
    except ImportError:  # no torch: the same function the CLI calls
        quantize_model_dir(out)
    else:
        assert export_main(["--int8", "--out", str(out)]) == 0
    return out


def _clouds(model, seed):
    """A source and a target in the unit frame, as register() hands them to the model: a rotated noisy blob."""
    rng = np.random.default_rng(seed)
    shape = rng.standard_normal((1024, 3)) * [0.6, 0.4, 0.2]
    a = np.deg2rad(25.0)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    src = shape[rng.choice(1024, 512, replace=False)] + rng.normal(0, 0.01, (512, 3))
    tgt = shape[rng.choice(1024, 512, replace=False)] @ R.T + [0.1, -0.05, 0.0]
    norm = fit_normalization(src, tgt)
    return resample(norm.to_unit(src), model.n_points, rng), resample(norm.to_unit(tgt), model.n_points, rng)


def test_int8_graphs_are_listed_with_their_sha256(int8_dir):
    card = read_card(int8_dir, precision="int8")
    for name in INT8_GRAPHS:
        assert (int8_dir / name).is_file() and len(card["files"][name]) == 64
    made_from = card["quantization"]["from"]
    assert {"embed.onnx", "score.onnx"} <= set(made_from) and all(made_from[n] == card["files"][n] for n in made_from)
    assert ("head.int8.onnx" in card["files"]) == ("head.onnx" in made_from)
    assert "score_fine.int8.onnx" in card["files"] and "score_fine.onnx" in made_from  # the fine phase's call too
    # Every MatMul/Gemm of the fp32 graph with a constant weight becomes an integer MatMul, but those of the
    # nodes kept fp32 (the MLP heads, the reward layer): counted on the fp32 graph, independently of the int8 one.
    import onnx

    from pranet.model.quantize import FP32_PREFIXES, OP_TYPES

    def quantizable(graph_file):
        g = onnx.load(str(int8_dir / graph_file)).graph
        constants = {i.name for i in g.initializer}
        for n in g.node:  # constant propagation: a node of constants only (Identity, Transpose...) is constant
            if all(i in constants for i in n.input if i):
                constants.update(n.output)
        return sum(
            n.op_type in OP_TYPES and n.input[1] in constants and not n.name.startswith(FP32_PREFIXES) for n in g.node
        )

    # The cross-attention block's weights stay fp32 (FP32_PREFIXES): the int8 score graph is about 0.8 of the fp32 one.
    assert (int8_dir / "score.int8.onnx").stat().st_size < 0.85 * (int8_dir / "score.onnx").stat().st_size
    ops = {
        g: [n.op_type for n in onnx.load(str(int8_dir / g)).graph.node] for g in ("score.int8.onnx", "head.int8.onnx")
    }
    assert quantizable("score.onnx") > 0
    assert (
        ops["score.int8.onnx"].count("MatMulInteger") == quantizable("score.onnx")
        and "MatMulInteger" not in ops["head.int8.onnx"]
    )


def test_the_matchings_exact_linear_maps_stay_fp32(int8_dir):
    """Horn's matrix of H and the rotation of q qᵀ are constant products inside the matching: quantizing their
    operands would bend every estimated rotation. Only the learned projections of the matching are int8."""
    import onnx

    g = onnx.load(str(int8_dir / "score.int8.onnx")).graph
    quantized = [n.name for n in g.node if n.op_type in ("MatMulInteger", "DynamicQuantizeLinear")]
    assert any(name.startswith("/correspondence/q/") for name in quantized)
    assert not [name for name in quantized if name.startswith(("/correspondence/MatMul", "/correspondence/Flatten"))]


def test_int8_rewards_are_close_to_fp32(int8_dir):
    fp32 = RewardModel.load(int8_dir, threads=1)
    int8 = RewardModel.load(int8_dir, threads=1, precision="int8")
    assert int8.precision == "int8" and int8.sha256 != fp32.sha256  # the service reports which graphs it runs
    diffs, same_argmax = [], 0
    for seed in range(4):
        src, tgt = _clouds(fp32, seed)
        s32, s8 = fp32.score_fn(tgt), int8.score_fn(tgt)
        for r32, r8 in [(s32(src, tgt), s8(src, tgt)), (s32.fine(src, tgt), s8.fine(src, tgt))]:
            assert r8.shape == r32.shape and np.isfinite(r8).all()
            diffs.append(np.abs(r32 - r8).max())
            same_argmax += int(np.argmax(r32) == np.argmax(r8))
    # 7-bit weights (reduce_range), MLP heads in fp32: max |diff| 0.004-0.012 on an AVX2-only CPU (pranet-cpu
    # 1.1.0, rewards of order 0.18). Full-range weights saturate on AVX2 (0.04-0.066), int8 heads drift by up
    # to 0.04: this bound catches either.
    assert max(diffs) < 0.02, diffs
    assert same_argmax >= 6


def test_sha256_check_covers_the_int8_graphs(int8_dir, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(int8_dir, bad)
    data = bytearray((bad / "score.int8.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (bad / "score.int8.onnx").write_bytes(bytes(data))
    with pytest.raises(ModelLoadError, match="score.int8.onnx: sha256"):
        RewardModel.load(bad, precision="int8")
    RewardModel.load(bad, threads=1)  # the fp32 graphs are intact and still load

    (bad / "embed.int8.onnx").unlink()
    with pytest.raises(ModelLoadError, match="no int8 graphs"):
        RewardModel.load(bad, precision="int8")
    assert RewardModel.load(default_model_dir(), precision="int8").precision == "int8"  # shipped with int8 graphs


def test_stale_int8_graphs_are_refused(int8_dir, tmp_path):
    """int8 graphs made from other fp32 graphs than the card lists (a re-export since) do not load."""
    stale = tmp_path / "stale"
    shutil.copytree(int8_dir, stale)
    card = json.loads((stale / "card.json").read_text())
    card["quantization"]["from"]["score.onnx"] = "0" * 64
    (stale / "card.json").write_text(json.dumps(card))
    with pytest.raises(ModelLoadError, match="stale"):
        RewardModel.load(stale, precision="int8")
    with pytest.raises(ValueError, match="precision"):
        RewardModel.load(int8_dir, precision="fp16")


def test_service_loads_the_precision_it_is_told(int8_dir, monkeypatch, tmp_path):
    pytest.importorskip("pydantic_settings")
    from pranet.service.settings import Settings
    from pranet.service.state import ServiceState

    monkeypatch.setenv("PRANET_PRECISION", "int8")
    monkeypatch.setenv("PRANET_MODEL_DIR", str(int8_dir))
    settings = Settings()
    assert settings.precision == "int8" and Settings(precision="fp32").precision == "fp32"
    state = ServiceState(settings)
    state.load()
    assert state.model is not None and state.model.precision == "int8", state.model_error
    fp32_only = tmp_path / "fp32"
    shutil.copytree(int8_dir, fp32_only)
    (fp32_only / "embed.int8.onnx").unlink()
    monkeypatch.setenv("PRANET_MODEL_DIR", str(fp32_only))
    state = ServiceState(Settings())
    state.load()
    assert state.model is None and "no int8 graphs" in (state.model_error or "")
    monkeypatch.setenv("PRANET_PRECISION", "fp16")
    with pytest.raises(ValueError):
        Settings()
