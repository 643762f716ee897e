import json
import shutil

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")

from pranet.core.actions import build_action_table  # noqa: E402
from pranet.core.knn import knn_indices  # noqa: E402
from pranet.engine.runtime import ModelLoadError, RewardModel, default_model_dir, read_card  # noqa: E402
from pranet.model.config import NetConfig  # noqa: E402
from pranet.model.export import export_model  # noqa: E402
from pranet.model.network import RewardNet  # noqa: E402

ANALYTIC = {  # the 2.x networks: Sinkhorn matching and the analytic reward layer
    "n_points": 128,
    "pool": "maxmean",
    "correspondence": True,
    "matching": "sinkhorn",
    "reward_head": "analytic",
    "match_passes": 3,
}
NETS = {
    "mlp heads (1.x)": NetConfig(n_points=128, pool="maxmean", correspondence=True),
    "analytic rewards (2.x)": NetConfig(**ANALYTIC),
    "with an overlap head": NetConfig(**ANALYTIC, overlap_head=True),
    "with point-pair features": NetConfig(**ANALYTIC, point_pair_features=True),
    "with local first-layer edges": NetConfig(**ANALYTIC, local_edges=True),
}


@pytest.fixture(scope="module", params=list(NETS))
def exported(request, tmp_path_factory):
    torch.manual_seed(0)
    table = build_action_table()
    cfg = NETS[request.param]
    net = RewardNet(cfg, table).eval()
    if cfg.point_pair_features:  # their last layer starts at zero: give the features a say in the scores
        torch.nn.init.normal_(net.embedding.point_pairs.net[2].weight, std=0.5)
    out = tmp_path_factory.mktemp("model")
    card = {
        "name": "test",
        "version": "0",
        "preset": "test",
        "n_points": 128,
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
    export_model(net, out, card)
    return net, out


def test_torch_and_onnxruntime_agree(exported):
    net, out = exported
    model = RewardModel.load(out, threads=1)
    rng = np.random.default_rng(0)
    for n_src, n_tgt in [(128, 128), (100, 173)]:  # dynamic point counts
        src = rng.standard_normal((n_src, 3)).astype(np.float32) * 0.4
        tgt = rng.standard_normal((n_tgt, 3)).astype(np.float32) * 0.4 + 0.1
        ort_rewards = model.score_fn(tgt)(src, tgt)
        with torch.no_grad():
            ref = net(
                torch.from_numpy(src[None]),
                torch.from_numpy(knn_indices(src[None], 16)),
                torch.from_numpy(tgt[None]),
                torch.from_numpy(knn_indices(tgt[None], 16)),
            )[0].numpy()
        np.testing.assert_allclose(ort_rewards, ref, rtol=1e-4, atol=1e-5)


def test_batched_score_matches_single(exported):
    _, out = exported
    model = RewardModel.load(out, threads=1)
    rng = np.random.default_rng(1)
    srcs = rng.standard_normal((3, 128, 3)).astype(np.float32)
    tgt = rng.standard_normal((128, 3)).astype(np.float32)
    tf, tc, _ = model.embed(tgt)
    knn = knn_indices(srcs, model.k)
    batch = model.score(srcs, knn, np.repeat(tgt[None], 3, 0), np.repeat(tf, 3, 0), np.repeat(tc, 3, 0))
    # 3e-5: a batch runs other float32 kernels than one cloud, and the Horn solve's repeated squaring amplifies
    # their rounding in an untrained network's rewards (1.9e-5 on one of 24 with local first-layer edges).
    for i in range(3):
        np.testing.assert_allclose(batch[i], model.score_fn(tgt)(srcs[i], tgt), rtol=1e-4, atol=3e-5)


def test_metadata_and_card(exported):
    import onnx

    _, out = exported
    card = read_card(out)
    meta = {p.key: p.value for p in onnx.load(str(out / "score.onnx")).metadata_props}
    assert (
        json.loads(meta["actions"])["fingerprint"] == build_action_table().fingerprint == card["actions"]["fingerprint"]
    )
    assert json.loads(meta["n_points"]) == 128 and json.loads(meta["preset"]) == "test"


def test_corrupt_missing_and_mismatched_models_are_refused(exported, tmp_path):
    _, out = exported
    bad = tmp_path / "bad"
    shutil.copytree(out, bad)
    data = bytearray((bad / "score.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (bad / "score.onnx").write_bytes(bytes(data))
    with pytest.raises(ModelLoadError, match="sha256"):
        RewardModel.load(bad)
    (bad / "score.onnx").unlink()
    with pytest.raises(ModelLoadError, match="missing"):
        RewardModel.load(bad)
    with pytest.raises(ModelLoadError, match="no model card"):
        RewardModel.load(tmp_path / "nowhere")
    mism = tmp_path / "mismatch"
    shutil.copytree(out, mism)
    card = json.loads((mism / "card.json").read_text())
    card["actions"]["fingerprint"] = "0" * 64
    (mism / "card.json").write_text(json.dumps(card))
    with pytest.raises(ModelLoadError, match="action table mismatch"):
        RewardModel.load(mism)


def test_shipped_model_loads_and_matches_this_action_table():
    model = RewardModel.load(default_model_dir())
    assert model.card["actions"]["fingerprint"] == build_action_table(model.card["actions"]["scales"]).fingerprint
    assert model.schedule == (20, 40) and len(model.table) == 24
    tgt = np.random.default_rng(0).standard_normal((model.n_points, 3))
    assert np.isfinite(model.score_fn(tgt)(tgt, tgt)).all()


def test_shipped_model_is_its_committed_checkpoint():
    """The shipped graphs compute what the checkpoint named in the card computes (and that file is the one
    the card hashed): the trained weights in the repository come from the repository's own training run."""
    from pathlib import Path

    from pranet.model.export import load_checkpoint, sha256_file

    card = read_card(default_model_dir())
    ck_path = Path(__file__).resolve().parents[2] / card["checkpoint"]["path"]
    assert ck_path.is_file(), f"{ck_path}: the checkpoint of the shipped model is not committed"
    assert sha256_file(ck_path) == card["checkpoint"]["sha256"]
    net, ck = load_checkpoint(ck_path, card["net"].get("inference_passes") or None)  # the rounds the graph runs
    assert ck["epoch"] + 1 == card["training"]["epochs_completed"] and ck["val_loss"] == card["training"]["val_loss"]
    model = RewardModel.load(default_model_dir(), threads=1)
    rng = np.random.default_rng(3)
    src = rng.standard_normal((model.n_points, 3)).astype(np.float32) * 0.4
    tgt = src @ np.array([[0.8, -0.6, 0.0], [0.6, 0.8, 0.0], [0.0, 0.0, 1.0]], np.float32).T + 0.05
    # The target is the source's own points moved, so the twin term (the card's twin_matching) is in play.
    from pranet.core.twins import twin_similarity
    from pranet.model.network import ScoreGraph

    src_knn, tgt_knn = knn_indices(src[None], model.k), knn_indices(tgt[None], model.k)
    twin = None
    if model.twins is not None:
        settings = {key: model.twins[key] for key in ("k", "sigma", "weight")}
        twin = torch.from_numpy(twin_similarity(src, src_knn[0], tgt, tgt_knn[0], **settings)[None])
    with torch.no_grad():
        tf, tc = net.embed(torch.from_numpy(tgt[None]), torch.from_numpy(tgt_knn))
        s, k, t = (torch.from_numpy(a) for a in (src[None], src_knn, tgt[None]))
        ref = ScoreGraph(net)(s, k, t, tf, tc, twin)[0][0].numpy()
    np.testing.assert_allclose(model.score_fn(tgt)(src, tgt), ref, rtol=1e-4, atol=1e-5)


def _torch_rewards(net, src, tgt, k=16):
    with torch.no_grad():
        return net(
            torch.from_numpy(src[None]),
            torch.from_numpy(knn_indices(src[None], k)),
            torch.from_numpy(tgt[None]),
            torch.from_numpy(knn_indices(tgt[None], k)),
        )[0].numpy()


def test_translated_sources_are_rescored_by_the_head_alone(exported):
    """After a translation the runtime runs only head.onnx on the cached pair features; the rewards are the
    network's for the translated source (torch reference), and a rotation brings back a full call."""
    from scipy.spatial.transform import Rotation

    net, out = exported
    assert net.cfg.center_inputs and "head.onnx" in read_card(out)["files"]
    model = RewardModel.load(out, threads=1)
    rng = np.random.default_rng(4)
    src = rng.standard_normal((128, 3)) * 0.4
    tgt = (src @ Rotation.from_euler("z", 30, degrees=True).as_matrix().T + 0.2).astype(np.float32)
    fn = model.score_fn(tgt)
    R = Rotation.from_euler("x", 10, degrees=True).as_matrix()
    moves = [np.zeros(3), [0.1, 0, 0], [0.1, -0.1, 0], "rotate", [0.1, -0.1, 0.01], [0.1, -0.1, 0.02]]
    poses, pose = [], src.copy()
    for move in moves:
        pose = (pose - pose.mean(0)) @ R.T + pose.mean(0) if isinstance(move, str) else pose + np.asarray(move)
        poses.append(pose)
    got = [fn(p, tgt) for p in poses]
    assert fn.calls == {"full": 2, "head": 4, "fine": 0, "match": 0}  # first call and the rotation are full calls
    for p, g in zip(poses, got, strict=True):
        np.testing.assert_allclose(g, _torch_rewards(net, p.astype(np.float32), tgt), rtol=1e-4, atol=2e-5)
    # The translation changes the rewards (the head sees the offset): the cached path is not a stale answer.
    assert np.abs(got[1] - got[0]).max() > 1e-3
    plain = RewardModel.load(out, threads=1, reuse_translations=False).score_fn(tgt)
    for p, g in zip(poses, got, strict=True):
        np.testing.assert_allclose(plain(p, tgt), g, rtol=1e-4, atol=2e-5)
    assert plain.calls == {"full": 6, "head": 0, "fine": 0, "match": 0}


def test_models_without_a_head_graph_still_load(exported, tmp_path):
    """A model directory exported before head.onnx existed scores every step with score.onnx."""
    _, out = exported
    old = tmp_path / "old"
    shutil.copytree(out, old)
    (old / "head.onnx").unlink()
    card = json.loads((old / "card.json").read_text())
    del card["files"]["head.onnx"]
    (old / "card.json").write_text(json.dumps(card))
    model = RewardModel.load(old, threads=1)
    tgt = np.random.default_rng(5).standard_normal((128, 3)).astype(np.float32)
    fn = model.score_fn(tgt)
    a, b = fn(tgt, tgt), fn(tgt + 0.1, tgt)
    assert fn.calls == {"full": 2, "head": 0, "fine": 0, "match": 0} and np.abs(a - b).max() > 1e-3


def test_batched_rows_that_only_moved_are_rescored_by_the_head(exported):
    """Global mode's batch: rows only translated since the previous call (also after the batch shrank) take the
    head path; rotated rows a full call; the rewards equal those of score.onnx for every row."""
    from scipy.spatial.transform import Rotation

    _, out = exported
    rng = np.random.default_rng(6)
    src = rng.standard_normal((128, 3)) * 0.4
    tgt = (src + 0.1).astype(np.float32)
    starts = np.stack([src @ Rotation.from_euler("y", a, degrees=True).as_matrix().T for a in (0, 40, 80)])
    turn = Rotation.from_euler("z", 10, degrees=True).as_matrix()
    second = starts + [0.1, 0.0, 0.0]  # every row translated
    second[1] = (starts[1] - starts[1].mean(0)) @ turn.T + starts[1].mean(0)  # ... except row 1, rotated
    third = second[[0, 2]] + [0.0, 0.01, 0.0]  # row 1 left the batch; the others translated again
    fast = RewardModel.load(out, threads=1).batch_score_fn(tgt)
    plain = RewardModel.load(out, threads=1, reuse_translations=False).batch_score_fn(tgt)
    for batch in (starts, second, third):
        np.testing.assert_allclose(fast(batch, tgt), plain(batch, tgt), rtol=1e-4, atol=2e-5)
    assert fast.calls == {"full": 3 + 1, "head": 2 + 2, "fine": 0, "match": 0} and plain.calls == {
        "full": 8,
        "head": 0,
        "fine": 0,
        "match": 0,
    }


def test_the_walks_pose_gives_the_networks_own_rewards(exported):
    """The walk (``core.agent``) scores actions in closed form from ``score.pose``: those rewards must be the ones
    the network's analytic layer returns for the same source (and the torch network's residual pose)."""
    from pranet.core.reward import true_rewards

    net, out = exported
    model = RewardModel.load(out, threads=1)
    rng = np.random.default_rng(3)
    tgt = rng.standard_normal((150, 3)).astype(np.float32) * 0.4
    sources = np.stack([rng.standard_normal((128, 3)).astype(np.float32) * 0.4 + 0.05 * b for b in range(3)])
    score = model.batch_score_fn(tgt)
    if not model.analytic:
        assert score.pose is None  # MLP heads: no pose, the walk is off and every step calls the network
        return
    rewards = score(sources, tgt)
    R_err, t_err = score.pose(sources, tgt)
    np.testing.assert_allclose(true_rewards(R_err, t_err, model.table), rewards, atol=2e-4)
    with torch.no_grad():
        R_ref, t_ref, _, _ = net.pose_and_rewards(
            torch.from_numpy(sources),
            torch.from_numpy(knn_indices(sources[:1], 16).repeat(3, axis=0)),
            torch.from_numpy(np.repeat(tgt[None], 3, axis=0)),
            torch.from_numpy(np.repeat(knn_indices(tgt[None], 16), 3, axis=0)),
        )
    np.testing.assert_allclose(R_err, R_ref.numpy(), atol=1e-4)
    np.testing.assert_allclose(t_err, t_ref.numpy(), atol=1e-4)
    assert score.calls["full"] == 6  # three rows scored, three posed


def test_more_matching_rounds_at_export_are_what_the_graph_runs(tmp_path):
    """``pranet-export --match-passes 5``: the committed checkpoint's graph with five rounds of matching computes what
    the torch network with ``inference_passes=5`` computes, and not what the trained three rounds compute. (Trained
    weights: with random ones, five rounds of an arbitrary matching amplify float32 differences.)"""
    from pathlib import Path

    from pranet.model.export import card_from_checkpoint, load_checkpoint

    card = read_card(default_model_dir())
    ck_path = Path(__file__).resolve().parents[2] / card["checkpoint"]["path"]
    net5, ck = load_checkpoint(ck_path, match_passes=5)
    net3, _ = load_checkpoint(ck_path)
    assert ck["config"]["net"]["inference_passes"] == 5
    export_model(net5, tmp_path, card_from_checkpoint(ck, "test", "0"))
    assert read_card(tmp_path)["net"]["inference_passes"] == 5
    model = RewardModel.load(tmp_path, threads=1)
    rng = np.random.default_rng(5)
    src = rng.standard_normal((model.n_points, 3)).astype(np.float32) * 0.4
    tgt = src @ np.array([[0.8, -0.6, 0.0], [0.6, 0.8, 0.0], [0.0, 0.0, 1.0]], np.float32).T + 0.05
    args = [torch.from_numpy(a) for a in (src[None], knn_indices(src[None], 16), tgt[None], knn_indices(tgt[None], 16))]
    with torch.no_grad():
        ref5, ref3 = net5(*args)[0].numpy(), net3(*args)[0].numpy()
    ort = model.score_fn(tgt)(src, tgt)
    np.testing.assert_allclose(ort, ref5, rtol=1e-4, atol=1e-5)
    assert np.abs(ref5 - ref3).max() > 1e-3


def test_the_fine_graph_is_the_torch_fine_call(exported):
    """``score_fine.onnx`` (analytic networks): the runtime's ``score.fine`` computes what torch's fine-phase call
    computes (``ScoreGraph(net, FINE_ROUNDS)``), which is not the trained call; it counts its own calls, and every
    row goes through the graph (no head re-scoring: its pair features change with a translation)."""
    from pranet.model.config import FINE_ROUNDS, format_rounds
    from pranet.model.network import ScoreGraph

    net, out = exported
    model = RewardModel.load(out, threads=1)
    rng = np.random.default_rng(9)
    tgt = rng.standard_normal((150, 3)).astype(np.float32) * 0.4
    src = rng.standard_normal((128, 3)).astype(np.float32) * 0.4 + 0.05
    score = model.batch_score_fn(tgt)
    if not model.analytic:
        assert score.fine is None and "score_fine.onnx" not in read_card(out)["files"]
        return
    assert read_card(out)["fine_matching"]["rounds"] == format_rounds(FINE_ROUNDS)
    sources = np.stack([src, src + np.float32(0.03)])  # the second only translated
    fine = score.fine(sources, tgt)
    with torch.no_grad():
        tf, tc = net.embed(torch.from_numpy(tgt[None]), torch.from_numpy(knn_indices(tgt[None], 16)))
        graph = ScoreGraph(net, FINE_ROUNDS)
        tp = torch.from_numpy(tgt[None])
        knn = torch.from_numpy(knn_indices(src[None], 16))  # a translation keeps the graph
        ref = [graph(torch.from_numpy(s[None]), knn, tp, tf, tc)[0][0] for s in sources]
    # 1e-4: two rows run other float32 kernels than torch's one, and γ × 16 amplifies their rounding in an untrained
    # network (4.5e-5 seen on one of 48 rewards).
    np.testing.assert_allclose(fine, torch.stack(ref).numpy(), rtol=1e-4, atol=1e-4)
    assert np.abs(fine[0] - _torch_rewards(net, src, tgt)).max() > 1e-3  # not the trained call
    assert score.calls == {"full": 0, "head": 0, "fine": 2, "match": 0}
    single = model.score_fn(tgt)
    np.testing.assert_allclose(single.fine(src, tgt), fine[0], rtol=1e-4, atol=1e-4)


def test_a_translated_source_is_rescored_by_the_match_graph(exported):
    """``match_fine.onnx``: after a translation the fine scorer re-runs only the matching rounds, from the previous
    fine call's similarity and parameters, and returns what a full fine call returns for the translated source
    (itself torch's ``ScoreGraph(net, FINE_ROUNDS)``); a turned source goes through ``score_fine.onnx`` again. An
    overlap-head network has no match graph and runs every fine step in full."""
    from pranet.model.config import FINE_ROUNDS
    from pranet.model.network import ScoreGraph

    net, out = exported
    model = RewardModel.load(out, threads=1)
    if not model.has_fine_call:
        return
    card = read_card(out)
    if net.cfg.overlap_head:
        assert "match_fine.onnx" not in card["files"] and "match_graph" not in card["fine_matching"]
        assert model._match is None
        return
    assert card["fine_matching"]["match_graph"] == "match_fine.onnx" and "match_fine.onnx" in card["files"]
    rng = np.random.default_rng(11)
    tgt = rng.standard_normal((150, 3)).astype(np.float32) * 0.4
    src = rng.standard_normal((128, 3)).astype(np.float32) * 0.4
    c, s = np.cos(0.2), np.sin(0.2)
    turned = src @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32).T
    steps = [src, src + np.float32([0.03, 0.0, 0.0]), src + np.float32([0.03, -0.02, 0.01]), turned, turned + 0.02]
    fast, plain = (RewardModel.load(out, threads=1, reuse_translations=r).score_fn(tgt) for r in (True, False))
    got = np.stack([fast.fine(p, tgt) for p in steps])
    full = np.stack([plain.fine(p, tgt) for p in steps])
    assert fast.calls == {"full": 0, "head": 0, "fine": 2, "match": 3}, fast.calls
    assert plain.calls == {"full": 0, "head": 0, "fine": 5, "match": 0}, plain.calls
    np.testing.assert_allclose(got, full, rtol=1e-4, atol=1e-4)
    assert np.abs(got[1] - got[0]).max() > 1e-3  # the translation changed the rewards: not a copy of the last call
    with torch.no_grad():
        tf, tc = net.embed(torch.from_numpy(tgt[None]), torch.from_numpy(knn_indices(tgt[None], 16)))
        knn = torch.from_numpy(knn_indices(src[None], 16))
        graph = ScoreGraph(net, FINE_ROUNDS)
        ref = graph(torch.from_numpy(steps[2][None]), knn, torch.from_numpy(tgt[None]), tf, tc)[0][0].numpy()
    np.testing.assert_allclose(got[2], ref, rtol=1e-4, atol=1e-4)


def test_the_match_graph_reuses_rows_of_a_batch(exported):
    """Batched fine calls (the global mode's starts): each row is re-scored from the cached row it is a translation
    of, whatever its position in the batch, and a row new to the cache goes through ``score_fine.onnx``."""
    net, out = exported
    model = RewardModel.load(out, threads=1)
    if model._match is None:
        return
    rng = np.random.default_rng(12)
    tgt = rng.standard_normal((150, 3)).astype(np.float32) * 0.4
    a = rng.standard_normal((128, 3)).astype(np.float32) * 0.4
    b = a[:, [1, 0, 2]] * np.float32([1, -1, 1])  # a turned copy of a (a quarter turn about z)
    fast = model.batch_score_fn(tgt)
    fast.fine(np.stack([a, b]), tgt)
    moved = np.stack([b + 0.02, a - 0.01, a[:, [2, 1, 0]]])  # b and a translated (swapped), then a new orientation
    got = fast.fine(moved, tgt)
    assert fast.calls["fine"] == 3 and fast.calls["match"] == 2, fast.calls
    plain = RewardModel.load(out, threads=1, reuse_translations=False).batch_score_fn(tgt)
    np.testing.assert_allclose(got, plain.fine(moved, tgt), rtol=1e-4, atol=1e-4)


def test_every_exponent_of_the_shipped_graphs_is_floored():
    """Each Exp node of the shipped matching graphs reads a Clip's output (``model.matching.floored_exp``): an Exp of
    subnormal results costs onnxruntime 13× the time on CPUs without flush-to-zero, and a re-export that lost the
    floor would slow every network call again (docs/DESIGN.md, "Subnormal exponents")."""
    import onnx

    model_dir = default_model_dir()
    graphs = [g for g in read_card(model_dir)["files"] if g.endswith(".onnx")]
    checked = 0
    for name in graphs:
        graph = onnx.load(str(model_dir / name)).graph
        producer = {out: node for node in graph.node for out in node.output}
        for node in graph.node:
            if node.op_type == "Exp":
                assert producer[node.input[0]].op_type == "Clip", (name, node.name)
                checked += 1
    assert checked >= 33 * 2 + 44 * 2, checked  # score.onnx's rounds, the fine call's, in fp32 and int8
