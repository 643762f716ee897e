import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pranet.core.actions import build_action_table  # noqa: E402
from pranet.core.reward import true_rewards  # noqa: E402
from pranet.training.visited import visit, visit_steps  # noqa: E402

TABLE = build_action_table(((10.0, 0.1), (0.5, 0.01)))


class Prefers(torch.nn.Module):
    """A scripted network: the same rewards for every state, ``best`` highest, ``decoy`` higher still."""

    def __init__(self, best: str, decoy: str) -> None:
        super().__init__()
        self.rewards = torch.zeros(len(TABLE))
        self.rewards[TABLE.names.index(best)] = 1.0
        self.rewards[TABLE.names.index(decoy)] = 2.0

    def forward(self, src, src_knn, tgt, tgt_knn):
        return self.rewards.expand(len(src), -1)


def random_batch(rng: np.random.Generator, b: int = 3, n: int = 64):
    src = torch.from_numpy(rng.normal(size=(b, n, 3))).float()
    R = torch.from_numpy(np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(b)])).float()
    R = R * torch.sign(torch.linalg.det(R)).view(-1, 1, 1)  # proper rotations
    t = torch.from_numpy(rng.normal(scale=0.3, size=(b, 3))).float()
    knn = torch.zeros(b, n, 4, dtype=torch.long)
    return src, knn, src.clone(), knn, torch.zeros(b, len(TABLE)), R, t


def true_places(src, R, t):
    c = src.mean(dim=1, keepdim=True)
    return (src - c) @ R.transpose(1, 2) + c + t.unsqueeze(1)


def test_the_greedy_coarse_steps_move_the_source_and_keep_its_true_place():
    """Three steps of "rot+x:10deg" (the best coarse action; a fine one, scored higher, is not of the phase): every
    source point turns 30° about x about the unmoved centroid, and the labels still put it where it truly is."""
    batch = random_batch(np.random.default_rng(0))
    src, *_, R, t = batch
    out = visit(Prefers("rot+x:10deg", decoy="rot+y:0.5deg"), batch, TABLE, steps=3)
    moved, R2, t2, g2 = out[0], out[5], out[6], out[4]
    c = src.mean(dim=1, keepdim=True)
    a = np.deg2rad(30.0)
    Rx = torch.tensor([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]], dtype=torch.float32)
    torch.testing.assert_close(moved, (src - c) @ Rx.T + c, atol=1e-5, rtol=0)
    torch.testing.assert_close(true_places(moved, R2, t2), true_places(src, R, t), atol=1e-5, rtol=0)
    torch.testing.assert_close(t2, t)  # a rotation about the centroid leaves the translation still to do
    expected = true_rewards(R2.double().numpy(), t2.double().numpy(), TABLE)
    np.testing.assert_allclose(g2.numpy(), expected, atol=1e-6)


def test_a_translation_step_moves_the_centroid_and_takes_it_off_the_error():
    batch = random_batch(np.random.default_rng(1))
    src, *_, R, t = batch
    out = visit(Prefers("trans-z:0.1", decoy="trans+z:0.01"), batch, TABLE, steps=2)
    moved, R2, t2 = out[0], out[5], out[6]
    torch.testing.assert_close(moved, src - torch.tensor([0.0, 0.0, 0.2]), atol=1e-6, rtol=0)
    torch.testing.assert_close(t2, t + torch.tensor([0.0, 0.0, 0.2]), atol=1e-6, rtol=0)
    torch.testing.assert_close(R2, R)
    torch.testing.assert_close(true_places(moved, R2, t2), true_places(src, R, t), atol=1e-5, rtol=0)


def test_the_real_networks_own_steps_keep_the_labels_exact():
    """The real network (random weights; any policy must keep the bookkeeping exact) after five greedy steps."""
    from pranet.core.knn import knn_indices
    from pranet.model.network import RewardNet
    from pranet.training.config import PRESETS

    cfg = PRESETS["agent"].net
    net = RewardNet(cfg, TABLE)
    rng = np.random.default_rng(2)
    src, _, _, _, g, R, t = random_batch(rng, b=2, n=cfg.n_points)
    tgt = true_places(src, R, t)
    knn_s = torch.from_numpy(np.stack([knn_indices(s.numpy(), cfg.k) for s in src]))
    knn_t = torch.from_numpy(np.stack([knn_indices(s.numpy(), cfg.k) for s in tgt]))
    net.train()
    moved, *_, R2, t2 = visit(net, (src, knn_s, tgt, knn_t, g, R, t), TABLE, steps=5)
    assert net.training  # the mode is given back
    assert (moved - src).abs().max() > 0.05  # it moved
    torch.testing.assert_close(true_places(moved, R2, t2), tgt, atol=1e-4, rtol=0)


def test_visit_steps_cover_the_phase_in_the_given_fraction_of_batches():
    rng = np.random.default_rng(3)
    draws = np.array([visit_steps(rng, 0.25, 20) for _ in range(4000)])
    assert 0.22 < (draws > 0).mean() < 0.28
    assert set(draws[draws > 0]) == set(range(1, 21))
    assert all(visit_steps(rng, 0.0, 20) == 0 for _ in range(100))
