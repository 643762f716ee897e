"""The PRANet reward network in PyTorch (paper, "Architecture", Fig. 2).

DGCNN embedding (shared by source and target) -> Transformer cross-attention -> max-pool -> a shared
MLP -> separate rotation and translation heads, which output one reward per action of the table.

EdgeConv is computed in its decomposed form. The paper's edge function is
``h(x_i, x_j) = ReLU(w·x_i + v·x_j)``; ReLU is monotone, so
``max_j ReLU(w·x_i + v·x_j) = ReLU(w·x_i + max_j v·x_j)``: a point-wise linear map and a max over
gathered neighbours, with no ``(B, C, N, k)`` edge tensor through a Conv2d (about k times fewer
FLOPs). ``naive_edge_conv`` keeps the textbook form for the equivalence test.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from pranet.core.actions import ActionTable
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
    per-edge term ``(B, N, k, C_out)`` (the point-pair features' embedding), 0 without."""

    def __init__(self, c_in: int, c_out: int) -> None:
        super().__init__()
        self.w = nn.Linear(c_in, c_out)
        self.v = nn.Linear(c_in, c_out, bias=False)

    def forward(self, x: Tensor, idx: Tensor, edges: Tensor | None = None) -> Tensor:  # (B, N, C_in), (B, N, k)
        neighbors = gather_neighbors(self.v(x), idx)  # (B, N, k, C_out)
        if edges is not None:
            neighbors = neighbors + edges
        return torch.relu(self.w(x) + neighbors.amax(dim=2))

    def naive(self, x: Tensor, idx: Tensor) -> Tensor:
        """Textbook form: ReLU over the full edge tensor, then max over neighbours."""
        edges = self.w(x).unsqueeze(2) + gather_neighbors(self.v(x), idx)  # (B, N, k, C_out)
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
        self.convs = nn.ModuleList(EdgeConv(a, b) for a, b in zip(widths[:-1], widths[1:], strict=True))
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


class Attention(nn.Module):
    """Multi-head attention, written out so that it exports to plain ONNX ops."""

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"emb_dim {dim} is not divisible by heads {heads}")
        self.heads = heads
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)
        self.out = nn.Linear(dim, dim)

    def forward(self, x: Tensor, y: Tensor) -> Tensor:  # queries (B, N, D), keys/values (B, M, D)
        B, N, D = x.shape
        h = self.heads
        q = self.q(x).reshape(B, N, h, D // h).transpose(1, 2)  # (B, h, N, d)
        kv = self.kv(y).reshape(B, -1, 2, h, D // h).permute(2, 0, 3, 1, 4)  # (2, B, h, M, d)
        k, v = kv[0], kv[1]
        attn = torch.softmax(q @ k.transpose(-1, -2) * (D // h) ** -0.5, dim=-1)  # (B, h, N, M)
        return self.out((attn @ v).transpose(1, 2).reshape(B, N, D))


class TransformerBlock(nn.Module):
    """Pre-LayerNorm block: [self-attention], cross-attention to the other cloud, feed-forward."""

    def __init__(self, dim: int, heads: int, ff_dim: int, self_attention: bool) -> None:
        super().__init__()
        self.self_attn = Attention(dim, heads) if self_attention else None
        self.norm_self = nn.LayerNorm(dim) if self_attention else None
        self.norm_q = nn.LayerNorm(dim)
        self.norm_kv = nn.LayerNorm(dim)
        self.cross = Attention(dim, heads)
        self.norm_ff = nn.LayerNorm(dim)
        self.ff = nn.Sequential(nn.Linear(dim, ff_dim), nn.ReLU(), nn.Linear(ff_dim, dim))

    def forward(self, x: Tensor, y: Tensor) -> Tensor:
        if self.self_attn is not None and self.norm_self is not None:
            h = self.norm_self(x)
            x = x + self.self_attn(h, h)
        x = x + self.cross(self.norm_q(x), self.norm_kv(y))
        return x + self.ff(self.norm_ff(x))


def polar_rotation(H: Tensor, iterations: int = 20) -> Tensor:
    """Orthogonal polar factor of ``H: (B, 3, 3)`` by Newton-Schulz (SVD-free, so it exports to ONNX).

    ``X <- X (3I - XᵀX) / 2`` from ``H / ||H||_F`` converges to ``U Vᵀ`` of ``H = U S Vᵀ``.
    """
    X = H / (H.flatten(1).norm(dim=1).view(-1, 1, 1) + 1e-9)
    eye3 = torch.eye(3, dtype=H.dtype, device=H.device)
    for _ in range(iterations):
        X = 0.5 * X @ (3.0 * eye3 - X.transpose(1, 2) @ X)
    return X


class SoftCorrespondence(nn.Module):
    """Soft correspondences ``ŷ_i = Σ_j softmax_j(q_i·k_j) y_j`` of the source points in the target
    (DCP), summarised as the rotation ``R ≈ polar(Σ x_i ŷ_iᵀ)ᵀ`` and the mean residual ``ŷ - R x``.

    With ``ŷ_i = R x_i``: ``H = Σ x_i x_iᵀ Rᵀ = C Rᵀ``, whose orthogonal polar factor is ``Rᵀ``.
    """

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.q = nn.Linear(dim, dim)
        self.k = nn.Linear(dim, dim)
        self.scale = dim**-0.5

    def forward(self, fx: Tensor, fy: Tensor, x: Tensor, y: Tensor) -> Tensor:  # -> (B, 12)
        attn = torch.softmax(self.q(fx) @ self.k(fy).transpose(1, 2) * self.scale, dim=-1)  # (B, N, M)
        y_hat = attn @ y  # (B, N, 3)
        H = x.transpose(1, 2) @ y_hat / x.shape[1]  # (B, 3, 3)
        R = polar_rotation(H).transpose(1, 2)  # (B, 3, 3): x -> y
        residual = (y_hat - x @ R.transpose(1, 2)).mean(dim=1)  # (B, 3)
        return torch.cat([R.flatten(1), residual], dim=-1)


def horn_rotation(H: Tensor, squarings: int = 24) -> Tensor:
    """The rotation ``R`` maximising ``tr(R H)``, i.e. minimising ``Σ w_i ||R x_i - y_i||²`` for
    ``H = Σ w_i x_i y_iᵀ: (B, 3, 3)`` (Horn 1987, unit quaternions). Always a proper rotation.

    The quaternion is the top eigenvector of Horn's symmetric ``4×4`` matrix ``N``. ONNX has no
    eigensolver, so it is found by repeated squaring of ``N + ||N||_F I`` (positive semi-definite,
    same eigenvectors), which converges to ``q qᵀ`` as ``(λ₂/λ₁)^(2^k)``.
    """
    Sxx, Sxy, Sxz = H[:, 0, 0], H[:, 0, 1], H[:, 0, 2]
    Syx, Syy, Syz = H[:, 1, 0], H[:, 1, 1], H[:, 1, 2]
    Szx, Szy, Szz = H[:, 2, 0], H[:, 2, 1], H[:, 2, 2]
    N = torch.stack(
        [
            torch.stack([Sxx + Syy + Szz, Syz - Szy, Szx - Sxz, Sxy - Syx], -1),
            torch.stack([Syz - Szy, Sxx - Syy - Szz, Sxy + Syx, Szx + Sxz], -1),
            torch.stack([Szx - Sxz, Sxy + Syx, -Sxx + Syy - Szz, Syz + Szy], -1),
            torch.stack([Sxy - Syx, Szx + Sxz, Syz + Szy, -Sxx - Syy + Szz], -1),
        ],
        dim=-2,
    )  # (B, 4, 4)
    eye4 = torch.eye(4, dtype=H.dtype, device=H.device)
    M = N + (N.flatten(1).norm(dim=1).view(-1, 1, 1) + 1e-12) * eye4
    for _ in range(squarings):
        M = M @ M
        M = M / ((M * eye4).sum(dim=(1, 2)).view(-1, 1, 1) + 1e-30)  # ÷ trace (diagonal() exports to If nodes)
    # M ≈ q qᵀ: its column with the largest diagonal entry is q_i q, well away from zero.
    i = (M * eye4).sum(dim=-1).argmax(dim=-1)  # (B,)
    col = torch.gather(M, 2, i.view(-1, 1, 1).expand(-1, 4, 1)).squeeze(-1)  # (B, 4)
    w, x, y, z = (col / (col.norm(dim=-1, keepdim=True) + 1e-12)).unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        dim=-2,
    )


def logsumexp(x: Tensor, dim: int) -> Tensor:
    """``log Σ exp(x)`` along ``dim`` (kept), stabilised by the maximum. Written out because onnxruntime's
    ``ReduceLogSumExp`` kernel is several times slower on the CPU than these five element-wise ops."""
    m = x.amax(dim=dim, keepdim=True).detach()
    return m + (x - m).exp().sum(dim=dim, keepdim=True).log()


def sinkhorn_with_slack(logits: Tensor, iterations: int) -> Tensor:
    """Soft assignment ``(B, N, M)`` from ``logits: (B, N, M)`` (RPMNet, Eq. 7), in the log domain.

    A slack row and column with logit 0 absorb the points that have no counterpart: rows are
    normalised over the target points and the slack, columns over the source points and the slack. The slack
    row and column themselves are left as they are (masks, rather than slicing and concatenating the matrix).
    """
    padded = nn.functional.pad(logits, (0, 1, 0, 1), value=0.0)  # (B, N+1, M+1)
    real_rows = nn.functional.pad(torch.ones_like(logits[:, :, :1]), (0, 0, 0, 1))  # (B, N+1, 1): 0 on the slack
    real_cols = nn.functional.pad(torch.ones_like(logits[:, :1, :]), (0, 1, 0, 0))  # (B, 1, M+1)
    for _ in range(iterations):
        padded = padded - real_rows * logsumexp(padded, dim=2)
        padded = padded - real_cols * logsumexp(padded, dim=1)
    return padded[:, :-1, :-1].exp()


def weighted_procrustes(P: Tensor, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """``y ≈ R x + r`` from a soft assignment ``P: (B, N, M)`` of ``x: (B, N, 3)`` to ``y: (B, M, 3)``.

    Weights ``w_i = Σ_j P_ij`` and points ``ŷ_i = Σ_j P_ij y_j / w_i`` (RPMNet, Eq. 9) -> ``(R (B, 3, 3), r (B, 3))``.
    """
    w = P.sum(-1, keepdim=True)  # (B, N, 1)
    total = w.sum(1) + 1e-6  # (B, 1)
    x_mean = (w * x).sum(1) / total  # (B, 3)
    Py = P @ y  # (B, N, 3) = w_i ŷ_i
    y_mean = Py.sum(1) / total  # (B, 3)
    H = (x - x_mean.unsqueeze(1)).transpose(1, 2) @ (Py - w * y_mean.unsqueeze(1))  # Σ w_i x̃_i ỹ_iᵀ
    R = horn_rotation(H)
    return R, y_mean - (R @ x_mean.unsqueeze(-1)).squeeze(-1)


class SinkhornCorrespondence(nn.Module):
    """The residual pose ``y ≈ R x + r`` of the centred source ``x`` against the centred target ``y``.

    ``passes`` rounds of matching, each from the previous round's estimate (RPMNet's iterations, inside
    one call): affinity ``β·cos(q_i, k_j) - γ·||x̂_i - y_j||² - α`` with ``x̂`` the source moved by the
    estimate so far, Sinkhorn with slack, weighted Procrustes, composed onto the estimate. ``(β, γ, α) >= 0``
    of every round are predicted from the two pooled feature vectors (RPMNet's parameter network): the
    first round can lean on the features, the later ones on positions, which is what makes the
    estimate precise near alignment. In eval mode ``inference_passes`` (when set) rounds run, those beyond
    ``passes`` with the last round's parameters. Returns ``(B, 12)``: ``R`` flattened row-major, then ``r``.
    """

    # Scales of the predicted (β, γ, α): cosines are in [-1, 1] and squared distances between
    # neighbours of a unit-sized cloud of a few hundred points are ~1e-2.
    PARAM_SCALES = (20.0, 200.0, 2.0)

    # The overlap head starts out saying "every point has a counterpart" (log σ(4) = -0.02 on every logit), so a
    # network warm-started from one without it matches as before.
    OVERLAP_START_BIAS = 4.0

    def __init__(
        self,
        dim: int,
        pooled_dim: int,
        iterations: int,
        passes: int = 1,
        inference_passes: int = 0,
        overlap: bool = False,
    ) -> None:
        super().__init__()
        self.q = nn.Linear(dim, dim)
        self.k = nn.Linear(dim, dim)
        self.overlap: nn.Linear | None = None
        if overlap:
            self.overlap = nn.Linear(dim, 1)
            nn.init.zeros_(self.overlap.weight)
            nn.init.constant_(self.overlap.bias, self.OVERLAP_START_BIAS)
        # The last call's overlap logits ``((B, N), (B, M))``, for the training loss (None without the head).
        self.overlap_logits: tuple[Tensor, Tensor] | None = None
        self.passes = passes
        self.params = nn.Sequential(nn.Linear(2 * pooled_dim, 64), nn.ReLU(), nn.Linear(64, 3 * passes))
        self.register_buffer("param_scales", torch.tensor(self.PARAM_SCALES), persistent=False)
        self.iterations = iterations
        self.inference_passes = inference_passes

    def rounds(self) -> list[int]:
        """The parameter index of each matching round: the trained rounds, then (eval mode) the last one again."""
        n = self.passes if self.training or self.inference_passes <= 0 else self.inference_passes
        return [min(i, self.passes - 1) for i in range(n)]

    def forward(self, fx: Tensor, fy: Tensor, x: Tensor, y: Tensor, pooled: Tensor) -> Tensor:
        B = x.shape[0]
        params = nn.functional.softplus(self.params(pooled)).view(B, self.passes, 3) * self.param_scales
        qx = nn.functional.normalize(self.q(fx), dim=-1)  # (B, N, D)
        ky = nn.functional.normalize(self.k(fy), dim=-1)  # (B, M, D)
        similarity = qx @ ky.transpose(1, 2)  # (B, N, M)
        prior: Tensor | None = None  # (B, N, M) log-probabilities that both points of a match overlap
        if self.overlap is not None:
            ox, oy = self.overlap(fx).squeeze(-1), self.overlap(fy).squeeze(-1)  # (B, N), (B, M)
            self.overlap_logits = (ox, oy)
            prior = nn.functional.logsigmoid(ox).unsqueeze(2) + nn.functional.logsigmoid(oy).unsqueeze(1)
        y_sq = (y * y).sum(-1).unsqueeze(1)  # (B, 1, M)
        R = torch.eye(3, dtype=x.dtype, device=x.device).expand(B, 3, 3)
        r = torch.zeros_like(x[:, 0])
        for i in self.rounds():
            beta, gamma, alpha = (params[:, i, j].view(B, 1, 1) for j in range(3))
            moved = x @ R.transpose(1, 2) + r.unsqueeze(1)  # (B, N, 3)
            d2 = (moved * moved).sum(-1, keepdim=True) - 2.0 * moved @ y.transpose(1, 2) + y_sq  # (B, N, M)
            logits = beta * similarity - gamma * d2 - alpha
            P = sinkhorn_with_slack(logits if prior is None else logits + prior, self.iterations)
            R_i, r_i = weighted_procrustes(P, moved, y)
            R, r = R_i @ R, (R_i @ r.unsqueeze(-1)).squeeze(-1) + r_i
        return torch.cat([R.flatten(1), r], dim=-1)


class AnalyticRewards(nn.Module):
    """The rewards of every action from a residual pose, in closed form (``core.reward.true_rewards``).

    ``R: (B, 3, 3)`` still to apply about the source centroid, ``t: (B, 3)`` still to add to it ->
    ``(B, A)`` normalised per step-size scale.
    """

    def __init__(self, table: ActionTable) -> None:
        super().__init__()
        scale_of = torch.as_tensor([a.scale for a in table.actions])
        self.register_buffer("rotations", torch.as_tensor(table.rotations, dtype=torch.float32), persistent=False)
        self.register_buffer("translations", torch.as_tensor(table.translations, dtype=torch.float32), persistent=False)
        self.register_buffer("is_rotation", torch.as_tensor(table.is_rotation), persistent=False)
        masks = (scale_of.unsqueeze(0) == torch.arange(len(table.scales)).unsqueeze(1)).float()  # (S, A)
        self.register_buffer("scale_masks", masks, persistent=False)

    @staticmethod
    def _angle(R: Tensor) -> Tensor:
        """The rotation angle of ``R: (..., 3, 3)`` as ``2 atan(sin θ / (1 + cos θ))``, with ``sin θ`` from the
        antisymmetric part. A fine rotation reward is the difference of two angles 0.5° apart; ``arccos`` of the
        trace resolves small angles to ``1e-7 / sin θ`` in float32 (1e-4 of the reward), this to ``1e-7 θ``."""
        cos = (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) / 2.0
        vx = R[..., 2, 1] - R[..., 1, 2]
        vy = R[..., 0, 2] - R[..., 2, 0]
        vz = R[..., 1, 0] - R[..., 0, 1]
        sin = (vx * vx + vy * vy + vz * vz + 1e-30).sqrt() / 2.0
        return 2.0 * torch.atan(sin / (1.0 + cos).clamp(min=1e-12))

    def forward(self, R: Tensor, t: Tensor) -> Tensor:
        rot_before = self._angle(R)  # (B,)
        rot_after = self._angle(torch.einsum("bij,akj->baik", R, self.rotations))  # (B, A): angle(R R_aᵀ)
        trans_before = t.norm(dim=-1)  # (B,)
        trans_after = (t.unsqueeze(1) - self.translations.unsqueeze(0)).norm(dim=-1)  # (B, A)
        rewards = torch.where(
            self.is_rotation.unsqueeze(0),
            rot_before.unsqueeze(1) - rot_after,
            trans_before.unsqueeze(1) - trans_after,
        )
        norms = ((rewards * rewards) @ self.scale_masks.T).sqrt() @ self.scale_masks  # (B, A): its scale's norm
        return rewards / norms.clamp(min=1e-12)


def mlp(dims: tuple[int, ...]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(dims[:-1], dims[1:], strict=True):
        layers += [nn.Linear(a, b), nn.ReLU()]
    return nn.Sequential(*layers)


class RewardNet(nn.Module):
    """Scores every action of ``table`` for a (source, target) pair: ``rewards: (B, A)``."""

    def __init__(self, cfg: NetConfig, table: ActionTable) -> None:
        super().__init__()
        self.cfg = cfg
        self.embedding = DGCNN(cfg)
        D = self.embedding.out_dim
        self.blocks = nn.ModuleList(
            TransformerBlock(D, cfg.heads, cfg.ff_dim, cfg.self_attention) for _ in range(cfg.blocks)
        )
        pooled = D * (2 if cfg.pool == "maxmean" else 1)
        self._pooled_dims = 2 * pooled  # source and target pooled vectors, first in the MLP input
        extra = 3 if cfg.center_inputs else 0
        self.correspondence: nn.Module | None = None
        if cfg.correspondence:
            self.correspondence = (
                SinkhornCorrespondence(
                    D, pooled, cfg.sinkhorn_iters, cfg.match_passes, cfg.inference_passes, cfg.overlap_head
                )
                if cfg.matching == "sinkhorn"
                else SoftCorrespondence(D)
            )
        extra += 12 if cfg.correspondence else 0
        self.analytic = AnalyticRewards(table) if cfg.reward_head == "analytic" else None
        if self.analytic is None:  # the paper's MLP heads (an analytic network has no learned head)
            self.shared = mlp((2 * pooled + extra, *cfg.mlp_shared))
            width = cfg.mlp_shared[-1]
            n_rot, n_trans = len(table.rotation_indices), len(table.translation_indices)
            self.rotation_head = nn.Sequential(mlp((width, *cfg.mlp_head)), nn.Linear(cfg.mlp_head[-1], n_rot))
            self.translation_head = nn.Sequential(mlp((width, *cfg.mlp_head)), nn.Linear(cfg.mlp_head[-1], n_trans))
        # Heads output [rotations..., translations...]; this permutation puts them in table order.
        order = torch.cat([torch.as_tensor(table.rotation_indices), torch.as_tensor(table.translation_indices)])
        self.register_buffer("table_order", torch.argsort(order), persistent=False)

    def embed(self, points: Tensor, knn: Tensor) -> tuple[Tensor, Tensor]:
        """``points: (B, N, 3)``, ``knn: (B, N, k)`` -> ``(features (B, N, D), centroid (B, 3))``."""
        centroid = points.mean(dim=1)
        if self.cfg.center_inputs:
            points = points - centroid.unsqueeze(1)
        return self.embedding(points, knn), centroid

    def _pool(self, x: Tensor) -> Tensor:
        if self.cfg.pool == "maxmean":
            return torch.cat([x.amax(dim=1), x.mean(dim=1)], dim=-1)
        return x.amax(dim=1)

    def pair_features(
        self,
        src: Tensor,
        src_centroid: Tensor,
        tgt: Tensor,
        tgt_centroid: Tensor,
        src_points: Tensor | None = None,
        tgt_points: Tensor | None = None,
    ) -> Tensor:
        """Embeddings of both clouds -> ``(B, P)``: the MLP input except the centroid offset.

        With ``center_inputs`` this does not depend on where the source is, only on its orientation: a
        translation action leaves it unchanged (``head`` alone re-scores), which the runtime exploits.
        ``src_points``/``tgt_points`` (``(B, N, 3)``, ``(B, M, 3)``) are needed with ``correspondence``.
        """
        for block in self.blocks:
            # Φ_X = F_X + φ(F_X, F_Y), Φ_Y = F_Y + φ(F_Y, F_X) with shared weights (paper, "Architecture").
            src, tgt = block(src, tgt), block(tgt, src)
        parts = [self._pool(src), self._pool(tgt)]
        if self.correspondence is not None:
            if src_points is None or tgt_points is None:
                raise ValueError("this network needs the points of both clouds (correspondence=True)")
            x = src_points - src_centroid.unsqueeze(1)
            y = tgt_points - tgt_centroid.unsqueeze(1)
            if isinstance(self.correspondence, SinkhornCorrespondence):
                pose = self.correspondence(src, tgt, x, y, torch.cat(parts, dim=-1))
                if self.analytic is not None:
                    return pose  # the analytic head needs nothing else
                parts.append(pose)
            else:
                parts.append(self.correspondence(src, tgt, x, y))
        return torch.cat(parts, dim=-1)

    def residual_pose(self, pair: Tensor, offset: Tensor) -> tuple[Tensor, Tensor]:
        """Analytic head: ``pair: (B, 12)``, ``offset: (B, 3)`` -> ``(R_err (B, 3, 3), t_err (B, 3))``.

        ``y ≈ R x + r`` in centred coordinates, so the source centroid must move by ``r - offset``
        (offset = source − target centroid): the state of ``core.reward``.
        """
        return pair[:, :9].reshape(-1, 3, 3), pair[:, 9:12] - offset

    def head(self, pair: Tensor, offset: Tensor) -> Tensor:
        """``pair: (B, P)`` from ``pair_features``, ``offset: (B, 3)`` = source − target centroid -> ``(B, A)``.

        The offset is used only with ``center_inputs`` (it sits after the two pooled vectors, as in training).
        With the analytic head, the rewards are computed in closed form from the residual pose.
        """
        if self.analytic is not None:
            return self.analytic(*self.residual_pose(pair, offset))
        if self.cfg.center_inputs:
            n = self._pooled_dims
            pair = torch.cat([pair[:, :n], offset, pair[:, n:]], dim=-1)
        h = self.shared(pair)
        out = torch.cat([self.rotation_head(h), self.translation_head(h)], dim=-1)
        return out[:, self.table_order]

    def score(
        self,
        src: Tensor,
        src_centroid: Tensor,
        tgt: Tensor,
        tgt_centroid: Tensor,
        src_points: Tensor | None = None,
        tgt_points: Tensor | None = None,
    ) -> Tensor:
        """Embeddings of both clouds -> ``rewards: (B, A)`` in action-table order (``pair_features`` + ``head``)."""
        pair = self.pair_features(src, src_centroid, tgt, tgt_centroid, src_points, tgt_points)
        return self.head(pair, src_centroid - tgt_centroid)

    def pose_and_rewards(
        self, source: Tensor, source_knn: Tensor, target: Tensor, target_knn: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Analytic networks: ``(R_err (B, 3, 3), t_err (B, 3), source centroid (B, 3), rewards (B, A))``."""
        src, src_c = self.embed(source, source_knn)
        tgt, tgt_c = self.embed(target, target_knn)
        pair = self.pair_features(src, src_c, tgt, tgt_c, source, target)
        offset = src_c - tgt_c
        R, t = self.residual_pose(pair, offset)
        return R, t, src_c, self.head(pair, offset)

    def forward(self, source: Tensor, source_knn: Tensor, target: Tensor, target_knn: Tensor) -> Tensor:
        return self.score(*self.embed(source, source_knn), *self.embed(target, target_knn), source, target)


class EmbedGraph(nn.Module):
    """ONNX graph 1: ``(points, knn) -> (features, centroid)``; the service runs it once for the target."""

    def __init__(self, net: RewardNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, points: Tensor, knn: Tensor) -> tuple[Tensor, Tensor]:
        return self.net.embed(points, knn)


class ScoreGraph(nn.Module):
    """ONNX graph 2: ``(points, knn, target_points, target_features, target_centroid) -> (rewards, pair_features)``;
    once a step.

    ``target_points`` is only an input of networks with ``correspondence``. ``pair_features`` is what
    ``HeadGraph`` needs to re-score the same source after a translation (``center_inputs`` networks).
    """

    def __init__(self, net: RewardNet) -> None:
        super().__init__()
        self.net = net

    def forward(
        self, points: Tensor, knn: Tensor, target_points: Tensor, target_features: Tensor, target_centroid: Tensor
    ) -> tuple[Tensor, Tensor]:
        src, centroid = self.net.embed(points, knn)
        pair = self.net.pair_features(src, centroid, target_features, target_centroid, points, target_points)
        return self.net.head(pair, centroid - target_centroid), pair


class HeadGraph(nn.Module):
    """ONNX graph 3: ``(pair_features (B, P), offset (B, 3)) -> rewards (B, A)``: the MLP heads alone.

    For a ``center_inputs`` network, a translated source has the same ``pair_features``; only the centroid
    offset (source − target centroid) changes, so the runtime re-scores it with this graph (microseconds).
    """

    def __init__(self, net: RewardNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, pair_features: Tensor, offset: Tensor) -> Tensor:
        return self.net.head(pair_features, offset)
