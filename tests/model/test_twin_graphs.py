"""The twin term in the exported graphs (``core.twins``; ``pranet-export --twins``): torch/ONNX parity of the score
and fine graphs with it, the match graph's reuse keeping it, and a clean pair it changes."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")

from pranet.core.actions import build_action_table  # noqa: E402
from pranet.core.knn import knn_indices  # noqa: E402
from pranet.core.twins import twin_similarity  # noqa: E402
from pranet.engine.runtime import RewardModel, read_card  # noqa: E402
from pranet.model.config import FINE_ROUNDS, NetConfig  # noqa: E402
from pranet.model.export import export_model  # noqa: E402
from pranet.model.network import RewardNet, ScoreGraph  # noqa: E402

CFG = NetConfig(
    n_points=128, pool="maxmean", correspondence=True, matching="sinkhorn", reward_head="analytic", match_passes=3
)


def card_of(cfg: NetConfig, table) -> dict:
    return {
        "name": "test",
        "version": "0",
        "preset": "test",
        "n_points": cfg.n_points,
        "k": cfg.k,
        "actions": {
            "scales": [list(s) for s in table.scales],
            "names": list(table.names),
            "fingerprint": table.fingerprint,
        },
        "schedule": [20, 40],
        "net": cfg.to_dict(),
        "training": {},
    }


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    torch.manual_seed(0)
    table = build_action_table()
    net = RewardNet(CFG, table).eval()
    with_twins, without = tmp_path_factory.mktemp("twins"), tmp_path_factory.mktemp("plain")
    export_model(net, with_twins, card_of(CFG, table), twins=True)
    export_model(net, without, card_of(CFG, table))
    return net, with_twins, without


def clean_pair(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A target that is the source's own points turned 40° about z and shifted, in another order."""
    rng = np.random.default_rng(seed)
    src = (rng.standard_normal((128, 3)) * 0.4).astype(np.float32)
    c, s = np.cos(np.deg2rad(40.0)), np.sin(np.deg2rad(40.0))
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], np.float32)
    return src, (src @ R.T + np.float32(0.05))[rng.permutation(128)]


def torch_call(net, src, tgt, rounds=None, twin=None):
    with torch.no_grad():
        tf, tc = net.embed(torch.from_numpy(tgt[None]), torch.from_numpy(knn_indices(tgt[None], 16)))
        term = None if twin is None else torch.from_numpy(twin[None])
        out = ScoreGraph(net, rounds)(
            torch.from_numpy(src[None]),
            torch.from_numpy(knn_indices(src[None], 16)),
            torch.from_numpy(tgt[None]),
            tf,
            tc,
            term,
        )
        return out[0][0].numpy()


def test_the_card_names_the_input_and_a_plain_export_has_none(exported):
    _, with_twins, without = exported
    assert read_card(with_twins)["twin_matching"] == {"input": "twin", "k": 8, "sigma": 0.05, "weight": 1.0}
    assert RewardModel.load(with_twins, threads=1).twins is not None
    plain = RewardModel.load(without, threads=1)
    assert plain.twins is None and "twin" not in plain._score_inputs and "twin_matching" not in plain.card


def test_the_score_graph_with_twins_is_torchs_call_with_the_term(exported):
    net, with_twins, _ = exported
    model = RewardModel.load(with_twins, threads=1)
    src, tgt = clean_pair()
    twin = twin_similarity(src, knn_indices(src, 16), tgt, knn_indices(tgt, 16))
    got = model.score_fn(tgt)(src, tgt)
    np.testing.assert_allclose(got, torch_call(net, src, tgt, twin=twin), rtol=1e-4, atol=1e-5)
    assert np.abs(got - torch_call(net, src, tgt)).max() > 1e-3  # the term changes the call on a clean pair
    with pytest.raises(ValueError, match="twin"):
        feats, cen, knn = model.embed(tgt)
        model.score(src[None], knn_indices(src[None], 16), tgt[None], feats, cen)


def test_the_fine_graph_keeps_the_term_and_so_does_the_match_graph(exported):
    """The source, then the source only translated: the first through score_fine.onnx, the second through
    match_fine.onnx from the first's similarity, which carries the term: both are torch's fine call with it."""
    net, with_twins, _ = exported
    model = RewardModel.load(with_twins, threads=1)
    src, tgt = clean_pair(1)
    twin = twin_similarity(src, knn_indices(src, 16), tgt, knn_indices(tgt, 16))
    score = model.batch_score_fn(tgt)
    sources = [src, src + np.float32(0.03)]
    got = np.concatenate([score.fine(s[None], tgt) for s in sources])  # two steps: a call, then a translation
    ref = np.stack([torch_call(net, s, tgt, FINE_ROUNDS, twin) for s in sources])
    np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-4)
    assert score.calls["fine"] == 1 and score.calls["match"] == 1
