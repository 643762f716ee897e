import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pranet.core.actions import build_action_table  # noqa: E402
from pranet.core.knn import knn_indices  # noqa: E402
from pranet.model.config import PAPER_NET, NetConfig  # noqa: E402
from pranet.model.embedding import EdgeConv, gather_neighbors  # noqa: E402
from pranet.model.network import RewardNet  # noqa: E402


def textbook_edge_conv(x, idx, weight, bias):
    """DGCNN's EdgeConv: Conv2d over edge features [x_j - x_i, x_i] (B, 2C, N, k), ReLU, max over k."""
    B, N, C = x.shape
    xj = gather_neighbors(x, idx)  # (B, N, k, C)
    xi = x.unsqueeze(2).expand_as(xj)
    edges = torch.cat([xj - xi, xi], dim=-1).permute(0, 3, 1, 2)  # (B, 2C, N, k)
    conv = torch.nn.functional.conv2d(edges, weight[:, :, None, None], bias)
    return torch.relu(conv).amax(dim=-1).transpose(1, 2)  # (B, N, C_out)


def test_decomposed_edge_conv_equals_the_textbook_form():
    torch.manual_seed(0)
    B, N, C, Cout, k = 3, 64, 16, 32, 10
    x = torch.randn(B, N, C)
    idx = torch.from_numpy(knn_indices(x.numpy(), k))
    weight = torch.randn(Cout, 2 * C) * 0.3  # [θ1 | θ2] acting on [x_j - x_i, x_i]
    bias = torch.randn(Cout) * 0.1
    conv = EdgeConv(C, Cout)
    with torch.no_grad():  # θ1 x_j + (θ2 - θ1) x_i: v = θ1, w = θ2 - θ1
        conv.v.weight.copy_(weight[:, :C])
        conv.w.weight.copy_(weight[:, C:] - weight[:, :C])
        conv.w.bias.copy_(bias)
    ref = textbook_edge_conv(x, idx, weight, bias)
    torch.testing.assert_close(conv(x, idx), ref, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(conv.naive(x, idx), ref, atol=1e-5, rtol=1e-5)


def test_a_local_edge_conv_is_the_textbook_form_on_offsets_only():
    """``local``: DGCNN's Conv2d over ``[x_j - x_i]`` alone (the ``x_i`` half of the weight is zero)."""
    torch.manual_seed(0)
    B, N, C, Cout, k = 2, 48, 3, 16, 8
    x = torch.randn(B, N, C)
    idx = torch.from_numpy(knn_indices(x.numpy(), k))
    conv = EdgeConv(C, Cout, local=True)
    with torch.no_grad():
        conv.bias.normal_(std=0.1)
    weight = torch.cat([conv.v.weight, torch.zeros(Cout, C)], dim=1)
    ref = textbook_edge_conv(x, idx, weight.detach(), conv.bias.detach())
    torch.testing.assert_close(conv(x, idx), ref, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(conv.naive(x, idx), ref, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("local", [True, False])
def test_local_edges_make_the_embedding_blind_to_where_the_cloud_sits(local):
    """What ``local_edges`` is for: one surface point, two crops with different centroids, the same features. A
    translated cloud (the kNN graph unchanged) embeds identically with it, and differently without."""
    torch.manual_seed(2)
    table = build_action_table()
    net = RewardNet(NetConfig(n_points=64, center_inputs=False, local_edges=local), table).eval()
    pts = torch.randn(1, 64, 3)
    knn = torch.from_numpy(knn_indices(pts.numpy(), 16))
    with torch.no_grad():
        a, _ = net.embed(pts, knn)
        b, _ = net.embed(pts + torch.tensor([0.15, -0.1, 0.05]), knn)
    assert torch.allclose(a, b, atol=1e-5) == local


@pytest.mark.parametrize(
    "cfg", [NetConfig(n_points=64), NetConfig(n_points=64, pool="maxmean", blocks=2, self_attention=True)]
)
def test_reward_net_shapes_and_point_order_invariance(cfg):
    """Rewards are a function of two point *sets*: re-ordering either cloud (and its kNN graph) changes nothing."""
    torch.manual_seed(1)
    table = build_action_table()
    net = RewardNet(cfg, table).eval()
    src, tgt = torch.randn(2, 64, 3), torch.randn(2, 80, 3)
    sk = torch.from_numpy(knn_indices(src.numpy(), cfg.k))
    tk = torch.from_numpy(knn_indices(tgt.numpy(), cfg.k))
    ps, pt = torch.randperm(64), torch.randperm(80)
    with torch.no_grad():
        out = net(src, sk, tgt, tk)
        shuffled = net(
            src[:, ps],
            torch.from_numpy(knn_indices(src[:, ps].numpy(), cfg.k)),
            tgt[:, pt],
            torch.from_numpy(knn_indices(tgt[:, pt].numpy(), cfg.k)),
        )
    assert out.shape == (2, len(table))
    torch.testing.assert_close(shuffled, out, atol=1e-5, rtol=1e-4)
    assert not torch.allclose(out[0], out[1])  # and they do depend on the clouds


def test_centered_embedding_is_translation_invariant_but_offset_reaches_the_heads():
    torch.manual_seed(2)
    net = RewardNet(NetConfig(n_points=64), build_action_table()).eval()
    src, tgt = torch.randn(1, 64, 3), torch.randn(1, 64, 3)
    sk = torch.from_numpy(knn_indices(src.numpy(), 16))
    tk = torch.from_numpy(knn_indices(tgt.numpy(), 16))
    with torch.no_grad():
        f1, _ = net.embed(src, sk)
        f2, _ = net.embed(src + torch.tensor([0.3, -0.2, 0.1]), sk)
        torch.testing.assert_close(f1, f2, atol=1e-5, rtol=1e-5)
        r1 = net(src, sk, tgt, tk)
        r2 = net(src + torch.tensor([0.3, -0.2, 0.1]), sk, tgt, tk)
    assert not torch.allclose(r1, r2)


def test_paper_preset_dynamic_graph_runs():
    cfg = NetConfig(
        **{
            **PAPER_NET.to_dict(),
            "n_points": 32,
            "k": 8,
            "edge_widths": (16, 16, 32, 32, 64),
            "emb_dim": 64,
            "ff_dim": 64,
            "mlp_shared": (32,),
            "mlp_head": (16,),
        }
    )
    net = RewardNet(cfg, build_action_table()).eval()
    x = torch.randn(1, 32, 3)
    k = torch.from_numpy(knn_indices(x.numpy(), 8))
    with torch.no_grad():
        assert net(x, k, x, k).shape == (1, 24)
    assert np.isfinite(net(x, k, x, k).detach().numpy()).all()


def test_polar_rotation_matches_svd():
    from scipy.spatial.transform import Rotation

    from pranet.model.matching import polar_rotation

    rng = np.random.default_rng(0)
    R = torch.from_numpy(Rotation.random(8, random_state=4).as_matrix())
    C = torch.from_numpy(np.stack([np.diag(rng.uniform(0.02, 1.0, 3)) for _ in range(8)]))
    H = C @ R.transpose(1, 2)  # the cross-covariance of exact correspondences y = R x
    torch.testing.assert_close(polar_rotation(H, iterations=40).transpose(1, 2), R, atol=1e-6, rtol=1e-6)


def kabsch(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least squares ``y ≈ R x + t`` by SVD with the reflection guard (Umeyama)."""
    w = w / w.sum()
    xm, ym = w @ x, w @ y
    H = (x - xm).T @ ((y - ym) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, ym - R @ xm


def test_horn_rotation_matches_svd_kabsch_and_is_never_a_reflection():
    from scipy.spatial.transform import Rotation

    from pranet.model.matching import horn_rotation

    rng = np.random.default_rng(3)
    R = Rotation.random(16, random_state=5).as_matrix()
    x = rng.normal(size=(16, 40, 3)) * [1.0, 0.6, 0.3]
    y = np.einsum("bij,bnj->bni", R, x) + rng.normal(0.0, 0.3, x.shape)  # noisy: H is far from a rotation
    y[:4] = -y[:4]  # mirrored targets: the unconstrained optimum is a reflection
    xc, yc = x - x.mean(1, keepdims=True), y - y.mean(1, keepdims=True)
    H = torch.from_numpy(np.einsum("bni,bnj->bij", xc, yc))
    got = horn_rotation(H.float()).double().numpy()
    for b in range(16):
        expected, _ = kabsch(x[b], y[b], np.ones(40))
        np.testing.assert_allclose(got[b], expected, atol=2e-5)
        assert np.linalg.det(got[b]) == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize("scale", [1e-5, 1.0, 1e4])
def test_horn_rotation_holds_at_any_scale_of_h(scale):
    """The power iteration normalises only every few squarings: tiny and huge cross-covariances must still give
    Kabsch's rotation (no underflow or overflow in float32)."""
    from scipy.spatial.transform import Rotation

    from pranet.model.matching import horn_rotation

    rng = np.random.default_rng(6)
    R = Rotation.random(8, random_state=7).as_matrix()
    x = rng.normal(size=(8, 30, 3))
    y = np.einsum("bij,bnj->bni", R, x) + rng.normal(0.0, 0.05, x.shape)
    xc, yc = x - x.mean(1, keepdims=True), y - y.mean(1, keepdims=True)
    H = np.einsum("bni,bnj->bij", xc, yc) * scale
    got = horn_rotation(torch.from_numpy(H).float()).double().numpy()
    for b in range(8):
        expected, _ = kabsch(x[b], y[b], np.ones(30))
        np.testing.assert_allclose(got[b], expected, atol=2e-5)


def test_horn_rotation_of_nothing_matched_is_the_identity():
    """All mass in the slack gives ``H = 0``: the estimate must be "stay", not a degenerate matrix."""
    from pranet.model.matching import horn_rotation

    torch.testing.assert_close(horn_rotation(torch.zeros(2, 3, 3)), torch.eye(3).expand(2, 3, 3))


def test_rotation_from_the_quaternion_outer_product_is_scipys():
    """The linear map from ``q qᵀ`` to ``R`` (polarised from the written-out formula) against scipy, for unit and
    unnormalised quaternions (the homogeneous form divides by ``|q|²``)."""
    from scipy.spatial.transform import Rotation

    from pranet.model.matching import QUATERNION_OUTER_TO_R

    rng = np.random.default_rng(8)
    q = rng.normal(size=(20, 4)) * rng.uniform(0.1, 10.0, (20, 1))  # (w, x, y, z), any norm
    outer = np.einsum("bi,bj->bij", q, q).reshape(20, 16)
    got = (outer @ QUATERNION_OUTER_TO_R.numpy() / (q * q).sum(1, keepdims=True)).reshape(20, 3, 3)
    expected = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy: scalar last
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_analytic_rewards_equal_the_numpy_labels():
    from scipy.spatial.transform import Rotation

    from pranet.core.reward import true_rewards
    from pranet.model.network import AnalyticRewards

    table = build_action_table()
    rng = np.random.default_rng(4)
    axes = rng.normal(size=(32, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    R = Rotation.from_rotvec(axes * np.deg2rad(rng.uniform(0.3, 90.0, 32))[:, None]).as_matrix()
    t = rng.normal(0.0, 0.2, (32, 3))
    got = AnalyticRewards(table)(torch.from_numpy(R).float(), torch.from_numpy(t).float()).numpy()
    np.testing.assert_allclose(got, true_rewards(R, t, table), atol=2e-5)


def test_sinkhorn_with_slack_is_doubly_stochastic_and_drops_unmatched_points():
    from pranet.model.matching import sinkhorn_with_slack

    torch.manual_seed(5)
    logits = torch.randn(2, 7, 9) * 2.0
    logits[:, 0] = -30.0  # source point 0 matches nothing: it belongs to the slack column
    P = sinkhorn_with_slack(logits, 200)
    rows = P.sum(-1)
    cols = P.sum(-2)
    assert (rows <= 1.0 + 1e-5).all() and (cols <= 1.0 + 1e-5).all()
    assert rows[:, 0].max() < 1e-6
    # Brute-force check of the fixed point: the padded matrix's rows and columns (but the slack ones) sum to 1.
    padded = torch.nn.functional.pad(logits, (0, 1, 0, 1))
    # Sinkhorn's fixed point is diag(a) exp(L) diag(b); P must have that form on the real block.
    ratio = P / logits.exp()
    a = ratio[:, :, :1]
    b = ratio[:, :1, :] / a[:, :1, :]
    torch.testing.assert_close(ratio[:, 1:], (a * b)[:, 1:], atol=1e-4, rtol=1e-3)
    assert padded.shape == (2, 8, 10)


def test_sinkhorn_normalised_without_the_maximum_equals_the_fully_stabilised_one():
    """Only the first normalisation subtracts the maximum, and every exponent is floored (``EXP_FLOOR``); the result
    must be the textbook log-domain Sinkhorn's (torch's ``logsumexp`` at every normalisation), also for logits far
    beyond exp's float32 range."""
    from pranet.model.matching import sinkhorn_with_slack

    def textbook(logits, iterations):
        padded = torch.nn.functional.pad(logits, (0, 1, 0, 1))
        rows = torch.nn.functional.pad(torch.ones_like(logits[:, :, :1]), (0, 0, 0, 1))
        cols = torch.nn.functional.pad(torch.ones_like(logits[:, :1, :]), (0, 1, 0, 0))
        for _ in range(iterations):
            padded = padded - rows * torch.logsumexp(padded, dim=2, keepdim=True)
            padded = padded - cols * torch.logsumexp(padded, dim=1, keepdim=True)
        return padded[:, :-1, :-1].exp()

    torch.manual_seed(9)
    for scale, shift in [(1.0, 0.0), (50.0, 0.0), (300.0, -500.0), (300.0, 500.0)]:
        logits = torch.randn(2, 40, 50) * scale + shift
        got = sinkhorn_with_slack(logits, 5)
        assert torch.isfinite(got).all()
        torch.testing.assert_close(got, textbook(logits, 5), atol=1e-5, rtol=1e-4)


def analytic_net(n: int = 96) -> RewardNet:
    cfg = NetConfig(n_points=n, correspondence=True, matching="sinkhorn", reward_head="analytic", sinkhorn_iters=10)
    return RewardNet(cfg, build_action_table()).eval()


def test_analytic_net_recovers_a_small_pose_from_positions_alone():
    """With the feature term off and a sharp position term (an ICP-like soft match), the module's weighted
    Procrustes finds a 2° rotation and a translation of a clean copy: the residual pose is the truth."""
    from scipy.spatial.transform import Rotation

    net = analytic_net()
    with torch.no_grad():
        last = net.correspondence.params[-1]
        last.weight.zero_()
        last.bias.copy_(torch.tensor([-30.0, 200.0, 0.0]))  # β ≈ 0, γ = 4e4, α = 0
    rng = np.random.default_rng(7)
    src = rng.normal(size=(96, 3)) * [1.0, 0.6, 0.3]
    R = Rotation.from_rotvec(np.deg2rad(2.0) * np.array([1.0, -2.0, 0.5]) / np.sqrt(5.25)).as_matrix()
    tgt = (src - src.mean(0)) @ R.T + src.mean(0) + [0.05, -0.02, 0.03]
    s, t = torch.from_numpy(src[None]).float(), torch.from_numpy(tgt[None]).float()
    sk, tk = (torch.from_numpy(knn_indices(a.numpy(), 16)) for a in (s, t))
    with torch.no_grad():
        R_hat, t_hat, _, rewards = net.pose_and_rewards(s, sk, t, tk)
    np.testing.assert_allclose(R_hat[0].numpy(), R, atol=1e-4)
    np.testing.assert_allclose(t_hat[0].numpy(), [0.05, -0.02, 0.03], atol=1e-4)
    from pranet.core.reward import true_rewards

    np.testing.assert_allclose(
        rewards[0].numpy(), true_rewards(R, [0.05, -0.02, 0.03], build_action_table()), atol=2e-3
    )


def test_analytic_head_rescores_a_translated_source_from_its_pair_features():
    torch.manual_seed(8)
    net = analytic_net(64)
    src, tgt = torch.randn(1, 64, 3), torch.randn(1, 64, 3)
    sk, tk = (torch.from_numpy(knn_indices(a.numpy(), 16)) for a in (src, tgt))
    shift = torch.tensor([0.3, -0.2, 0.1])
    with torch.no_grad():
        sf, sc = net.embed(src, sk)
        tf, tc = net.embed(tgt, tk)
        pair = net.pair_features(sf, sc, tf, tc, src, tgt)
        R, t, _, _ = net.pose_and_rewards(src, sk, tgt, tk)
        R2, t2, _, moved = net.pose_and_rewards(src + shift, sk, tgt, tk)
        torch.testing.assert_close(R2, R, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(t2, t - shift, atol=1e-5, rtol=1e-5)  # the centroid must now move less
        torch.testing.assert_close(net.head(pair, sc + shift - tc), moved, atol=2e-4, rtol=1e-3)


def test_analytic_head_needs_sinkhorn_matching():
    with pytest.raises(ValueError, match="analytic"):
        NetConfig(correspondence=True, reward_head="analytic")


def test_rounds_beyond_the_trained_ones_run_at_inference_and_bring_an_icp_like_match_closer():
    """``inference_passes``: in eval mode the matching runs that many rounds, the extra ones with the last trained
    round's (β, γ, α); in training mode the trained rounds only. With a position-only match (an ICP-like soft
    match) from 12° off, one round leaves most of the error and the extra rounds take it further, as ICP's
    iterations do; ``inference_passes == match_passes`` is the trained function exactly."""
    from dataclasses import replace

    from scipy.spatial.transform import Rotation

    from pranet.core.metrics import isotropic_errors

    cfg = NetConfig(n_points=96, correspondence=True, matching="sinkhorn", reward_head="analytic", sinkhorn_iters=10)
    table = build_action_table()
    torch.manual_seed(0)
    trained = RewardNet(cfg, table).eval()
    with torch.no_grad():
        last = trained.correspondence.params[-1]
        last.weight.zero_()
        last.bias.copy_(torch.tensor([-30.0, 4.0, 0.0]))  # β ≈ 0, γ ≈ 800, α = 0: positions only
    rng = np.random.default_rng(3)
    src = rng.normal(size=(96, 3)) * [1.0, 0.6, 0.3]
    R = Rotation.from_rotvec(np.deg2rad(12.0) * np.array([1.0, -2.0, 0.5]) / np.sqrt(5.25)).as_matrix()
    tgt = (src - src.mean(0)) @ R.T + src.mean(0)
    s, t = torch.from_numpy(src[None]).float(), torch.from_numpy(tgt[None]).float()
    sk, tk = (torch.from_numpy(knn_indices(a.numpy(), 16)) for a in (s, t))
    truth = np.eye(4)
    truth[:3, :3] = R
    errors = {}
    for rounds in (0, 1, 4):
        net = RewardNet(replace(cfg, inference_passes=rounds), table).eval()
        net.load_state_dict(trained.state_dict())
        with torch.no_grad():
            R_hat, t_hat, _, _ = net.pose_and_rewards(s, sk, t, tk)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_hat[0].numpy(), t_hat[0].numpy()
        errors[rounds] = isotropic_errors(T, truth)[0]
        assert net.correspondence.train().rounds() == [(0, 1.0)]  # training runs the trained round only
    assert errors[1] == pytest.approx(errors[0], abs=1e-9)
    assert errors[4] < 0.5 * errors[1] and errors[1] > 1.0, errors


def position_only_net(passes: int = 3) -> RewardNet:
    """An analytic network whose every round matches on positions alone (β ≈ 0, γ ≈ 425, about the trained last
    round's): ICP-like. Sharper, a point a few hundredths off its counterpart goes to the slack."""
    cfg = NetConfig(
        n_points=96,
        correspondence=True,
        matching="sinkhorn",
        reward_head="analytic",
        sinkhorn_iters=10,
        match_passes=passes,
    )
    torch.manual_seed(0)
    net = RewardNet(cfg, build_action_table()).eval()
    with torch.no_grad():
        last = net.correspondence.params[-1]
        last.weight.zero_()
        last.bias.copy_(torch.tensor([-30.0, 2.0, 0.0] * passes))
    return net


def residual_of(net: RewardNet, src: np.ndarray, tgt: np.ndarray, rounds=None) -> tuple[np.ndarray, np.ndarray]:
    """``(R_err, t_err)`` of ``net``'s call on the pair (``rounds``: a fine-phase call on those rounds)."""
    s, t = torch.from_numpy(src[None]).float(), torch.from_numpy(tgt[None]).float()
    sk, tk = (torch.from_numpy(knn_indices(a.numpy(), 16)) for a in (s, t))
    with torch.no_grad():
        sf, sc = net.embed(s, sk)
        tf, tc = net.embed(t, tk)
        pair = net.pair_features(sf, sc, tf, tc, s, t, rounds)
        R, t_err = net.residual_pose(pair, sc - tc)
    return R[0].numpy(), t_err[0].numpy()


def test_explicit_rounds_are_the_trained_ones_and_a_gamma_factor_narrows_the_kernel():
    """``rounds``: the trained rounds named explicitly compute the trained call exactly; γ × 16 on them changes it."""
    torch.manual_seed(4)
    cfg = NetConfig(n_points=64, correspondence=True, matching="sinkhorn", reward_head="analytic", match_passes=3)
    corr = RewardNet(cfg, build_action_table()).eval().correspondence
    fx, fy = torch.randn(1, 64, 128), torch.randn(1, 70, 128)
    x, y = torch.randn(1, 64, 3) * 0.3, torch.randn(1, 70, 3) * 0.3
    pooled = torch.randn(1, 256)
    with torch.no_grad():
        trained = corr(fx, fy, x, y, pooled)
        named = corr(fx, fy, x, y, pooled, [(0, 1.0), (1, 1.0), (2, 1.0)])
        sharper = corr(fx, fy, x, y, pooled, [(0, 16.0), (1, 16.0), (2, 16.0)])
    torch.testing.assert_close(named, trained, atol=0.0, rtol=0.0)
    assert (sharper - trained).abs().max() > 1e-3
    with pytest.raises(ValueError, match="round"):
        corr(fx, fy, x, y, pooled, [(3, 1.0)])


def test_a_fine_call_matches_a_crop_where_it_lies():
    """A partial source (one side of the target, its own points) at the true pose: matched in place (the fine
    call), a sharp position-only match pairs every point with itself and the residual pose is the identity; matched
    about each cloud's own centroid (the trained call), the crop starts 0.1-0.3 from where it lies and the same match
    ends off."""
    from pranet.model.config import FINE_ROUNDS

    net = position_only_net()
    rng = np.random.default_rng(11)
    tgt = rng.normal(size=(160, 3)) * [1.0, 0.6, 0.3]
    src = tgt[tgt[:, 0] > -0.2][:96]  # a crop: its centroid is well off the target's
    assert np.linalg.norm(src.mean(0) - tgt.mean(0)) > 0.1
    R_fine, t_fine = residual_of(net, src, tgt, FINE_ROUNDS)
    np.testing.assert_allclose(R_fine, np.eye(3), atol=1e-4)
    np.testing.assert_allclose(t_fine, 0.0, atol=1e-4)
    R_own, t_own = residual_of(net, src, tgt)
    assert np.linalg.norm(t_own) > 0.02 or np.abs(R_own - np.eye(3)).max() > 0.02


def test_a_fine_call_sees_a_translation_and_ignores_a_shift_of_both_clouds():
    """The fine call's residual follows a translated source (its pair features depend on where the source is,
    so the runtime cannot re-score it with the head alone) and does not change when both clouds move together."""
    from pranet.model.config import FINE_ROUNDS

    net = position_only_net()
    rng = np.random.default_rng(12)
    src = rng.normal(size=(96, 3)) * [1.0, 0.6, 0.3]
    tgt = src[rng.permutation(96)]
    shift, both = np.array([0.02, -0.01, 0.015]), np.array([0.4, 0.3, -0.2])
    _, t0 = residual_of(net, src, tgt, FINE_ROUNDS)
    _, t1 = residual_of(net, src + shift, tgt, FINE_ROUNDS)
    _, t2 = residual_of(net, src + both, tgt + both, FINE_ROUNDS)
    np.testing.assert_allclose(t0, 0.0, atol=1e-4)
    np.testing.assert_allclose(t1, -shift, atol=1e-3)
    np.testing.assert_allclose(t2, t0, atol=1e-4)


def test_the_overlap_head_takes_the_points_it_calls_unshared_out_of_the_pose():
    """A position-only match of a cloud whose x > 0 half has moved 0.1 along x (a part the other cloud does not
    share): the estimate is dragged toward that half. An overlap head that scores those points as unshared (a
    feature channel marks them; its weight makes their logit -20) leaves them to the slack, and the estimate is
    the shared half's, the identity. A fresh head (weight 0, bias +4) matches almost as a network without one."""
    from pranet.model.matching import SinkhornCorrespondence

    torch.manual_seed(0)
    rng = np.random.default_rng(5)
    y = torch.from_numpy(rng.normal(size=(1, 128, 3)) * [1.0, 0.6, 0.3]).float()
    moved = (y[0, :, 0] > 0).float()  # (128,)
    x = y + 0.1 * moved.view(1, -1, 1) * torch.tensor([1.0, 0.0, 0.0])
    fx = torch.zeros(1, 128, 8)
    fx[0, :, 0] = moved  # the channel the head reads
    fy = torch.zeros(1, 128, 8)

    def estimate(overlap: bool, weight: float | None = None) -> torch.Tensor:
        match = SinkhornCorrespondence(8, 4, iterations=10, passes=1, overlap=overlap).eval()
        with torch.no_grad():
            match.params[-1].weight.zero_()
            match.params[-1].bias.copy_(torch.tensor([-30.0, -1.0, 0.0]))  # β ≈ 0, γ ≈ 63: positions only
            if weight is not None:
                match.overlap.weight.zero_()
                match.overlap.weight[0, 0] = weight
                match.overlap.bias.fill_(20.0)
            return match(fx, fy, x, y, torch.zeros(1, 8))[0, 9:]  # the translation

    plain, fresh, told = estimate(False), estimate(True), estimate(True, weight=-40.0)
    assert plain[0] < -0.02  # dragged: the estimate moves the source back by part of the moved half's 0.1
    torch.testing.assert_close(fresh, plain, atol=2e-3, rtol=0.0)
    assert told.abs().max() < 0.1 * plain.abs().max(), (told, plain)


def test_an_overlap_head_needs_sinkhorn_matching():
    with pytest.raises(ValueError, match="overlap_head"):
        NetConfig(correspondence=True, overlap_head=True)


def test_plane_normals_are_the_planes_normals_in_any_pose():
    """Points on the plane z = 0.02·(noise), turned and moved at random: every point's normal is the turned z axis
    (up to sign), as PCA of its neighbours gives it."""
    from pranet.model.embedding import plane_normals

    rng = np.random.default_rng(3)
    flat = np.c_[rng.uniform(-1, 1, (200, 2)), 0.002 * rng.normal(size=200)]
    for _ in range(3):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        pts = torch.from_numpy((flat @ q.T + rng.normal(size=3))[None]).float()
        n = plane_normals(pts, torch.from_numpy(knn_indices(pts.numpy(), 16)))[0].numpy()
        cos = np.abs(n @ q[:, 2])
        assert cos.min() > 0.99, cos.min()


def test_plane_normals_of_a_sphere_point_out():
    from pranet.model.embedding import plane_normals

    rng = np.random.default_rng(4)
    v = rng.normal(size=(500, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    n = plane_normals(torch.from_numpy(v[None]).float(), torch.from_numpy(knn_indices(v[None], 12)))[0].numpy()
    assert np.median(np.abs((n * v).sum(1))) > 0.99


def test_point_pair_features_do_not_change_with_the_pose():
    from pranet.model.embedding import point_pair_features

    rng = np.random.default_rng(6)
    pts = rng.normal(size=(1, 128, 3)) * [1.0, 0.6, 0.3]
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    moved = pts @ q.T + [0.3, -0.2, 0.5]
    knn = torch.from_numpy(knn_indices(pts, 16))  # the graph does not change with the pose either
    a = point_pair_features(torch.from_numpy(pts).float(), knn)
    b = point_pair_features(torch.from_numpy(moved).float(), knn)
    torch.testing.assert_close(a, b, atol=2e-3, rtol=0.0)
    assert a[..., 1:].max() <= 1.0 + 1e-6 and a[..., 0].max() > 0.1  # cosines, and lengths that are not all 0


def test_a_network_with_fresh_point_pair_features_scores_as_it_did_without():
    """The features' last layer starts at zero: warm-started from a network without them, the new one scores the
    same, and once that layer moves it does not."""
    table = build_action_table()
    torch.manual_seed(0)
    cfg = NetConfig(n_points=64, pool="maxmean", correspondence=True, matching="sinkhorn", reward_head="analytic")
    old = RewardNet(cfg, table).eval()
    new = RewardNet(NetConfig(**{**cfg.to_dict(), "point_pair_features": True}), table).eval()
    missing = new.load_state_dict(old.state_dict(), strict=False).missing_keys
    assert missing and all(k.startswith("embedding.point_pairs.") for k in missing)
    rng = np.random.default_rng(0)
    src, tgt = (torch.from_numpy(rng.normal(size=(1, 64, 3)) * 0.4).float() for _ in range(2))
    knn_s, knn_t = (torch.from_numpy(knn_indices(p.numpy(), cfg.k)) for p in (src, tgt))
    with torch.no_grad():
        torch.testing.assert_close(new(src, knn_s, tgt, knn_t), old(src, knn_s, tgt, knn_t))
        torch.nn.init.normal_(new.embedding.point_pairs.net[2].weight, std=1.0)
        assert not torch.allclose(new(src, knn_s, tgt, knn_t), old(src, knn_s, tgt, knn_t), atol=1e-3)


def test_the_floored_exponent_is_exp_where_float32_has_normal_numbers():
    """``floored_exp`` equals ``exp`` down to ``EXP_FLOOR`` and never returns a subnormal number below it (what makes
    onnxruntime's Exp slow); a logsumexp over a row of very negative logits still finds its largest term."""
    from pranet.model.matching import EXP_FLOOR, floored_exp, logsumexp

    x = torch.linspace(EXP_FLOOR, 30.0, 2001)
    torch.testing.assert_close(floored_exp(x), x.exp(), rtol=1e-6, atol=0.0)
    below = floored_exp(torch.tensor([-90.0, -100.0, -200.0, -1e4]))
    assert (below >= torch.finfo(torch.float32).tiny).all()
    assert (below <= torch.tensor(EXP_FLOOR).exp() * (1 + 1e-6)).all()
    row = torch.tensor([[-300.0, -150.0, -500.0]])
    torch.testing.assert_close(logsumexp(row, dim=1), torch.logsumexp(row, dim=1, keepdim=True))
