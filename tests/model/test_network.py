import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pranet.core.actions import build_action_table  # noqa: E402
from pranet.core.knn import knn_indices  # noqa: E402
from pranet.model.config import PAPER_NET, NetConfig  # noqa: E402
from pranet.model.network import EdgeConv, RewardNet, gather_neighbors  # noqa: E402


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


@pytest.mark.parametrize(
    "cfg", [NetConfig(n_points=64), NetConfig(n_points=64, pool="maxmean", blocks=2, self_attention=True)]
)
def test_reward_net_shapes_and_target_separability(cfg):
    torch.manual_seed(1)
    table = build_action_table()
    net = RewardNet(cfg, table).eval()
    src, tgt = torch.randn(2, 64, 3), torch.randn(2, 80, 3)
    sk = torch.from_numpy(knn_indices(src.numpy(), cfg.k))
    tk = torch.from_numpy(knn_indices(tgt.numpy(), cfg.k))
    with torch.no_grad():
        out = net(src, sk, tgt, tk)
        tf, tc = net.embed(tgt, tk)
        again = net.score(*net.embed(src, sk), tf, tc)
    assert out.shape == (2, len(table))
    torch.testing.assert_close(out, again)


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

    from pranet.model.network import polar_rotation

    rng = np.random.default_rng(0)
    R = torch.from_numpy(Rotation.random(8, random_state=4).as_matrix())
    C = torch.from_numpy(np.stack([np.diag(rng.uniform(0.02, 1.0, 3)) for _ in range(8)]))
    H = C @ R.transpose(1, 2)  # the cross-covariance of exact correspondences y = R x
    torch.testing.assert_close(polar_rotation(H, iterations=40).transpose(1, 2), R, atol=1e-6, rtol=1e-6)
