"""The point embedding of the reward network: DGCNN's EdgeConv layers over a kNN graph, with RPMNet's point-pair
features as an option for the first.

EdgeConv is computed in its decomposed form. The paper's edge function is
``h(x_i, x_j) = ReLU(w·x_i + v·x_j)``; ReLU is monotone, so
``max_j ReLU(w·x_i + v·x_j) = ReLU(w·x_i + max_j v·x_j)``: a point-wise linear map and a max over
gathered neighbours, with no ``(B, C, N, k)`` edge tensor through a Conv2d (about k times fewer
FLOPs). ``EdgeConv.naive`` keeps the textbook form for the equivalence test.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from pranet.model.config import NetConfig


def gather_neighbors(x: Tensor, idx: Tensor) -> Tensor:
    """``x: (B, N, C)``, ``idx: (B, N, k)`` -> ``(B, N, k, C)``."""
    B, N, C = x.shape
    k = idx.shape[-1]
    offset = (torch.arange(B, device=x.device) * N).view(B, 1, 1)
    flat = (idx + offset).reshape(-1)
    return x.reshape(B * N, C)[flat].reshape(B, N, k, C)


def feature_knn(x: Tensor, k: int) -> Tensor:
    """kNN in feature space: ``x: (B, N, C)`` -> ``(B, N, k)`` (DGCNN's dynamic graph)."""
    sq = (x * x).sum(-1)
    d2 = sq.unsqueeze(2) - 2.0 * x @ x.transpose(1, 2) + sq.unsqueeze(1)
    return (-d2).topk(k, dim=-1).indices


class EdgeConv(nn.Module):
    """``x_i' = ReLU(W x_i + b + max_j (V x_j + e_ij))`` over the neighbours ``j`` of ``i``; ``e_ij``: an optional
    per-edge term ``(B, N, k, C_out)`` (the point-pair features' embedding), 0 without.

    ``local``: ``W = -V``, i.e. ``ReLU(b + max_j V (x_j - x_i))``: only the offsets to the neighbours enter, so the
    output does not change when the cloud is translated (nor, on a layer that sees xyz, with the centroid a crop
    moves)."""

    def __init__(self, c_in: int, c_out: int, local: bool = False) -> None:
        super().__init__()
        self.w = None if local else nn.Linear(c_in, c_out)
        self.bias = nn.Parameter(torch.zeros(c_out)) if local else None
        self.v = nn.Linear(c_in, c_out, bias=False)

    def _centre_term(self, vx: Tensor, x: Tensor) -> Tensor:
        return self.bias - vx if self.w is None else self.w(x)

    def forward(self, x: Tensor, idx: Tensor, edges: Tensor | None = None) -> Tensor:  # (B, N, C_in), (B, N, k)
        vx = self.v(x)
        neighbors = gather_neighbors(vx, idx)  # (B, N, k, C_out)
        if edges is not None:
            neighbors = neighbors + edges
        return torch.relu(self._centre_term(vx, x) + neighbors.amax(dim=2))

    def naive(self, x: Tensor, idx: Tensor) -> Tensor:
        """Textbook form: ReLU over the full edge tensor, then max over neighbours."""
        vx = self.v(x)
        edges = self._centre_term(vx, x).unsqueeze(2) + gather_neighbors(vx, idx)  # (B, N, k, C_out)
        return torch.relu(edges).amax(dim=2)


def _cross(a: Tensor, b: Tensor) -> Tensor:
    """Row-wise cross product of ``(..., 3)`` tensors, written out (plain ONNX ops)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], dim=-1)


def plane_normals(points: Tensor, knn: Tensor) -> Tensor:
    """Unit normals ``(B, N, 3)`` (sign arbitrary) of the plane through each point's ``k`` neighbours: the
    eigenvector of their covariance with the smallest eigenvalue, in closed form, as ONNX has no eigensolver. The
    eigenvalue by the trigonometric solution of the characteristic cubic; the eigenvector as the longest cross
    product of two rows of ``C - λ I``, whose rows span the plane orthogonal to it."""
    nb = gather_neighbors(points, knn)  # (B, N, k, 3)
    centred = nb - nb.mean(dim=2, keepdim=True)
    C = centred.transpose(-1, -2) @ centred / knn.shape[-1]  # (B, N, 3, 3)
    eye3 = torch.eye(3, dtype=points.dtype, device=points.device)
    q = (C[..., 0, 0] + C[..., 1, 1] + C[..., 2, 2]) / 3.0
    off = C[..., 0, 1] ** 2 + C[..., 0, 2] ** 2 + C[..., 1, 2] ** 2
    diag = (C[..., 0, 0] - q) ** 2 + (C[..., 1, 1] - q) ** 2 + (C[..., 2, 2] - q) ** 2
    p = torch.sqrt((diag + 2.0 * off) / 6.0) + 1e-12
    Bm = (C - q[..., None, None] * eye3) / p[..., None, None]
    det = (
        Bm[..., 0, 0] * (Bm[..., 1, 1] * Bm[..., 2, 2] - Bm[..., 1, 2] * Bm[..., 2, 1])
        - Bm[..., 0, 1] * (Bm[..., 1, 0] * Bm[..., 2, 2] - Bm[..., 1, 2] * Bm[..., 2, 0])
        + Bm[..., 0, 2] * (Bm[..., 1, 0] * Bm[..., 2, 1] - Bm[..., 1, 1] * Bm[..., 2, 0])
    )
    phi = torch.acos((det / 2.0).clamp(-1.0 + 1e-6, 1.0 - 1e-6)) / 3.0
    smallest = q + 2.0 * p * torch.cos(phi + 2.0 * torch.pi / 3.0)
    M = C - smallest[..., None, None] * eye3
    crosses = torch.stack(
        [_cross(M[..., 0, :], M[..., 1, :]), _cross(M[..., 0, :], M[..., 2, :]), _cross(M[..., 1, :], M[..., 2, :])],
        dim=-2,
    )  # (B, N, 3, 3)
    lengths = (crosses * crosses).sum(-1)  # (B, N, 3)
    best = torch.nn.functional.one_hot(lengths.argmax(dim=-1), 3).to(points.dtype)
    n = (crosses * best.unsqueeze(-1)).sum(dim=-2)
    return n / (n.norm(dim=-1, keepdim=True) + 1e-12)


def point_pair_features(points: Tensor, knn: Tensor) -> Tensor:
    """RPMNet's point-pair features of every edge ``(i, j)`` of the graph, for unoriented normals:
    ``(|d|, |n_i·d̂|, |n_j·d̂|, |n_i·n_j|)`` with ``d = x_j - x_i``: ``(B, N, k, 4)``, unchanged by any rigid motion of
    the cloud and by which part of it the other cloud lacks (no centroid enters)."""
    n = plane_normals(points, knn)
    d = gather_neighbors(points, knn) - points.unsqueeze(2)  # (B, N, k, 3)
    length = d.norm(dim=-1, keepdim=True)
    unit = d / (length + 1e-9)
    n_i, n_j = n.unsqueeze(2), gather_neighbors(n, knn)
    return torch.cat(
        [
            length,
            (n_i * unit).sum(-1, keepdim=True).abs(),
            (n_j * unit).sum(-1, keepdim=True).abs(),
            (n_i * n_j).sum(-1, keepdim=True).abs(),
        ],
        dim=-1,
    )


class PointPairEdges(nn.Module):
    """Point-pair features embedded per edge, for the first EdgeConv's max. The last layer starts at zero, so a
    network warm-started from one without them computes exactly what it did until training moves it."""

    PPF_DIM = 4

    def __init__(self, c_out: int, hidden: int = 32) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(self.PPF_DIM, hidden), nn.ReLU(), nn.Linear(hidden, c_out))
        nn.init.zeros_(self.net[2].weight)
        nn.init.zeros_(self.net[2].bias)

    def forward(self, points: Tensor, knn: Tensor) -> Tensor:  # -> (B, N, k, c_out)
        return self.net(point_pair_features(points, knn))


class DGCNN(nn.Module):
    def __init__(self, cfg: NetConfig) -> None:
        super().__init__()
        widths = (3, *cfg.edge_widths)
        self.convs = nn.ModuleList(
            EdgeConv(a, b, local=cfg.local_edges and i == 0)
            for i, (a, b) in enumerate(zip(widths[:-1], widths[1:], strict=True))
        )
        self.point_pairs = PointPairEdges(cfg.edge_widths[0]) if cfg.point_pair_features else None
        self.dynamic = cfg.graph == "dynamic"
        self.k = cfg.k
        self.project = nn.Linear(sum(cfg.edge_widths), cfg.emb_dim) if cfg.project else None
        self.out_dim = cfg.emb_dim if cfg.project else cfg.edge_widths[-1]

    def forward(self, points: Tensor, knn: Tensor) -> Tensor:  # (B, N, 3), (B, N, k) -> (B, N, D)
        x, outs = points, []
        edges = self.point_pairs(points, knn) if self.point_pairs is not None else None
        for i, conv in enumerate(self.convs):
            idx = feature_knn(x, self.k) if self.dynamic and i > 0 else knn
            x = conv(x, idx, edges if i == 0 else None)
            outs.append(x)
        if self.project is None:
            return x
        return torch.relu(self.project(torch.cat(outs, dim=-1)))
