"""Soft correspondences between the two clouds' features, reduced to a pose: DCP's softmax attention (the 1.x
networks) or RPMNet's Sinkhorn matching with slack and a weighted Procrustes, in rounds (the 2.x networks). Every
solver is written out in plain tensor ops (no SVD or eigensolver), so that the graphs export to ONNX.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from pranet.model.config import MatchingRound


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


def horn_matrix_written_out(H: Tensor) -> Tensor:
    """Horn's symmetric ``4×4`` matrix ``N`` of ``H = Σ w_i x_i y_iᵀ: (B, 3, 3)``, entry by entry (Horn 1987)."""
    Sxx, Sxy, Sxz = H[:, 0, 0], H[:, 0, 1], H[:, 0, 2]
    Syx, Syy, Syz = H[:, 1, 0], H[:, 1, 1], H[:, 1, 2]
    Szx, Szy, Szz = H[:, 2, 0], H[:, 2, 1], H[:, 2, 2]
    return torch.stack(
        [
            torch.stack([Sxx + Syy + Szz, Syz - Szy, Szx - Sxz, Sxy - Syx], -1),
            torch.stack([Syz - Szy, Sxx - Syy - Szz, Sxy + Syx, Szx + Sxz], -1),
            torch.stack([Szx - Sxz, Sxy + Syx, -Sxx + Syy - Szz, Syz + Szy], -1),
            torch.stack([Sxy - Syx, Szx + Sxz, Syz + Szy, -Sxx - Syy + Szz], -1),
        ],
        dim=-2,
    )


def rotation_written_out(q: Tensor) -> Tensor:
    """The rotation of the quaternion ``q = (w, x, y, z): (B, 4)`` times ``|q|²``, entry by entry (the homogeneous
    form: every entry is a quadratic form in ``q``, so no unit norm is assumed)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            torch.stack([w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z], -1),
        ],
        dim=-2,
    )


def _quadratic_form_basis() -> Tensor:
    """``(16, 9)``: ``vec(R) = vec(q qᵀ) @ B`` for ``rotation_written_out``, by polarisation of its quadratic forms."""
    e = torch.eye(4, dtype=torch.float64)

    def at(q: Tensor) -> Tensor:
        return rotation_written_out(q.view(1, 4)).reshape(9)

    return torch.stack(
        [0.5 * (at(e[a] + e[b]) - at(e[a]) - at(e[b])) if a != b else at(e[a]) for a in range(4) for b in range(4)]
    )


# Both maps are linear, so each is one matrix product in the graph rather than the ~40 slicing, stacking and
# arithmetic nodes written out above, three matching rounds a call (onnxruntime's cost at 128 points is mostly per
# node: docs/DESIGN.md, "Fewer nodes in the network call").
HORN_N_MAP = horn_matrix_written_out(torch.eye(9, dtype=torch.float64).view(9, 3, 3)).reshape(9, 16)
QUATERNION_OUTER_TO_R = _quadratic_form_basis()

# Squarings between two normalisations of the power iteration. After one, ``M``'s trace is 1 and its eigenvalues are
# >= 0, so the largest is >= 1/4 and four squarings keep it >= 4^-16 ≈ 2e-10, far from float32's underflow.
SQUARINGS_PER_NORMALISATION = 4


def horn_rotation(H: Tensor, squarings: int = 24) -> Tensor:
    """The rotation ``R`` maximising ``tr(R H)``, i.e. minimising ``Σ w_i ||R x_i - y_i||²`` for
    ``H = Σ w_i x_i y_iᵀ: (B, 3, 3)`` (Horn 1987, unit quaternions). Always a proper rotation.

    The quaternion is the top eigenvector of Horn's symmetric ``4×4`` matrix ``N``. ONNX has no
    eigensolver, so it is found by repeated squaring of ``(N + ||N||_F I) / 4||N||_F`` (positive semi-definite,
    trace 1, same eigenvectors), which converges to ``q qᵀ`` as ``(λ₂/λ₁)^(2^k)``.
    """
    N = (H.flatten(1) @ HORN_N_MAP.to(H)).view(-1, 4, 4)
    eye4 = torch.eye(4, dtype=H.dtype, device=H.device)
    M = N / (4.0 * N.flatten(1).norm(dim=1).view(-1, 1, 1) + 1e-12) + 0.25 * eye4
    for k in range(1, squarings + 1):
        M = M @ M
        if k % SQUARINGS_PER_NORMALISATION == 0:
            M = M / ((M * eye4).sum(dim=(1, 2), keepdim=True) + 1e-30)  # ÷ trace (diagonal() exports to If nodes)
    # M ≈ q qᵀ: its column with the largest diagonal entry is q_i q, well away from zero; the rotation of that
    # column alone is a proper rotation even where M has not quite reached rank one.
    i = (M * eye4).sum(dim=-1).argmax(dim=-1)  # (B,)
    col = torch.gather(M, 2, i.view(-1, 1, 1).expand(-1, 4, 1))  # (B, 4, 1)
    outer = (col @ col.transpose(1, 2)).flatten(1)  # (B, 16)
    R = outer @ QUATERNION_OUTER_TO_R.to(H) / ((col * col).sum(dim=(1, 2)).view(-1, 1) + 1e-30)
    return R.view(-1, 3, 3)


# The floor of every exponent in the matching. Far-apart pairs under a narrow distance kernel have logits of -100
# and below, whose exp is a subnormal float32 or 0; onnxruntime's Exp takes 13× longer on those (4.7 against 0.35 ms
# per million entries on an Intel Xeon without flush-to-zero, which the calling thread of a one-thread session does
# not get: docs/DESIGN.md, "Subnormal exponents"). exp(-80) = 1.8e-35 is a normal float; a million of them add less
# than float32's resolution to any sum the matching takes (each is >= 1/((N+1)(M+1)): sinkhorn_with_slack).
EXP_FLOOR = -80.0


def floored_exp(x: Tensor) -> Tensor:
    """``exp(max(x, EXP_FLOOR))``: ``exp`` without subnormal results."""
    return x.clamp(min=EXP_FLOOR).exp()


def logsumexp(x: Tensor, dim: int, stabilised: bool = True) -> Tensor:
    """``log Σ exp(x)`` along ``dim`` (kept), stabilised by the maximum unless the caller knows ``exp`` cannot
    overflow or underflow to an all-zero sum. Written out because onnxruntime's ``ReduceLogSumExp`` kernel is
    several times slower on the CPU than these five element-wise ops."""
    if not stabilised:
        return floored_exp(x).sum(dim=dim, keepdim=True).log()
    m = x.amax(dim=dim, keepdim=True).detach()
    return m + floored_exp(x - m).sum(dim=dim, keepdim=True).log()


def sinkhorn_with_slack(logits: Tensor, iterations: int) -> Tensor:
    """Soft assignment ``(B, N, M)`` from ``logits: (B, N, M)`` (RPMNet, Eq. 7), in the log domain.

    A slack row and column with logit 0 absorb the points that have no counterpart: rows are
    normalised over the target points and the slack, columns over the source points and the slack. The slack
    row and column themselves are left as they are (masks, rather than slicing and concatenating the matrix).
    """
    padded = nn.functional.pad(logits, (0, 1, 0, 1), value=0.0)  # (B, N+1, M+1)
    real_rows = nn.functional.pad(torch.ones_like(logits[:, :, :1]), (0, 0, 0, 1))  # (B, N+1, 1): 0 on the slack
    real_cols = nn.functional.pad(torch.ones_like(logits[:, :1, :]), (0, 1, 0, 0))  # (B, 1, M+1)
    # Only the first normalisation needs the maximum: after it every entry is <= 0 (no overflow), and each row and
    # column keeps an entry above -log((N+1)(M+1)) (the slack's 0, or what the last normalisation left), so no
    # sum can underflow to zero. Two reductions and a subtraction fewer per normalisation.
    for k in range(iterations):
        padded = padded - real_rows * logsumexp(padded, dim=2, stabilised=k == 0)
        padded = padded - real_cols * logsumexp(padded, dim=1, stabilised=False)
    return floored_exp(padded[:, :-1, :-1])


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


# ``SinkhornCorrespondence.prepare``'s tensors: (similarity (B, N, M), params (B, passes, 3), overlap prior or None).
Prepared = tuple[Tensor, Tensor, Tensor | None]


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
        # The last call's ``prepare``d tensors (``forward``), for the fine phase's match-only graph.
        self.prepared: Prepared | None = None
        self.passes = passes
        self.params = nn.Sequential(nn.Linear(2 * pooled_dim, 64), nn.ReLU(), nn.Linear(64, 3 * passes))
        self.register_buffer("param_scales", torch.tensor(self.PARAM_SCALES), persistent=False)
        self.iterations = iterations
        self.inference_passes = inference_passes

    def rounds(self) -> list[MatchingRound]:
        """The rounds of a call: the trained ones, then (eval mode) the last one again, each with its own γ."""
        n = self.passes if self.training or self.inference_passes <= 0 else self.inference_passes
        return [(min(i, self.passes - 1), 1.0) for i in range(n)]

    def forward(
        self,
        fx: Tensor | None,
        fy: Tensor | None,
        x: Tensor,
        y: Tensor,
        pooled: Tensor | None,
        rounds: Sequence[MatchingRound] | None = None,
        prepared: Prepared | None = None,
        twin: Tensor | None = None,
    ) -> Tensor:
        """``rounds`` (default ``self.rounds()``): ``(parameter index, γ scale)`` per round, in order; a scale above 1
        narrows that round's distance kernel (the fine phase's schedule, ``model.config.FINE_ROUNDS``).
        ``prepared``: ``prepare``'s tensors of an earlier call on the same clouds (then ``fx``, ``fy`` and ``pooled``
        are not read): only the rounds run, on the clouds as placed now. ``twin``: ``core.twins``' term
        ``(B | 1, N, M)``, added to the feature similarity (``prepare``). Each call keeps its ``prepare``d tensors in
        ``self.prepared``. Both go through the module's call, so the exported nodes keep the ``/correspondence``
        names that ``model.quantize`` keeps in fp32."""
        # One batch size, read from x first, for both parts: the trace, and so score.onnx, stays node for node as it
        # was before the two parts were split.
        B = x.shape[0]
        if prepared is None:
            if fx is None or fy is None or pooled is None:
                raise ValueError("the features and pooled vectors are needed without prepared tensors")
            prepared = self.prepare(fx, fy, pooled, B, twin)
        self.prepared = prepared
        return self.match(*prepared, x, y, rounds, B)

    def prepare(
        self, fx: Tensor, fy: Tensor, pooled: Tensor, batch: int | None = None, twin: Tensor | None = None
    ) -> Prepared:
        """What the matching takes from the features: ``(similarity (B, N, M), params (B, passes, 3), prior)``, the
        cosines of the projected features (plus ``twin``, when given: ``core.twins``), every round's ``(β, γ, α)``
        and the overlap head's log-prior (``None`` without the head). None of it depends on where the clouds are, only
        on their shapes and orientations."""
        B = fx.shape[0] if batch is None else batch
        params = nn.functional.softplus(self.params(pooled)).view(B, self.passes, 3) * self.param_scales
        qx = nn.functional.normalize(self.q(fx), dim=-1)  # (B, N, D)
        ky = nn.functional.normalize(self.k(fy), dim=-1)  # (B, M, D)
        similarity = qx @ ky.transpose(1, 2)  # (B, N, M)
        if twin is not None:
            similarity = similarity + twin
        prior: Tensor | None = None  # (B, N, M) log-probabilities that both points of a match overlap
        if self.overlap is not None:
            ox, oy = self.overlap(fx).squeeze(-1), self.overlap(fy).squeeze(-1)  # (B, N), (B, M)
            self.overlap_logits = (ox, oy)
            prior = nn.functional.logsigmoid(ox).unsqueeze(2) + nn.functional.logsigmoid(oy).unsqueeze(1)
        return similarity, params, prior

    def match(
        self,
        similarity: Tensor,
        params: Tensor,
        prior: Tensor | None,
        x: Tensor,
        y: Tensor,
        rounds: Sequence[MatchingRound] | None = None,
        batch: int | None = None,
    ) -> Tensor:
        """The rounds of matching from ``prepare``'s tensors, on the clouds ``x: (B, N, 3)`` and ``y: (B, M, 3)`` as
        placed -> ``(B, 12)``. A translated source needs only this part again (``model.network.MatchGraph``)."""
        B = x.shape[0] if batch is None else batch
        rounds = self.rounds() if rounds is None else rounds
        if any(not 0 <= i < self.passes for i, _ in rounds):
            raise ValueError(f"rounds {list(rounds)} name a round this network has not ({self.passes} trained)")
        y_sq = (y * y).sum(-1).unsqueeze(1)  # (B, 1, M)
        R = torch.eye(3, dtype=x.dtype, device=x.device).expand(B, 3, 3)
        r = torch.zeros_like(x[:, 0])
        for i, gamma_scale in rounds:
            beta, gamma, alpha = (params[:, i, j].view(B, 1, 1) for j in range(3))
            moved = x @ R.transpose(1, 2) + r.unsqueeze(1)  # (B, N, 3)
            d2 = (moved * moved).sum(-1, keepdim=True) - 2.0 * moved @ y.transpose(1, 2) + y_sq  # (B, N, M)
            # A scale of 1 adds no node: the trained call's graph stays as it was exported before the fine schedule.
            logits = beta * similarity - (gamma * gamma_scale if gamma_scale != 1.0 else gamma) * d2 - alpha
            P = sinkhorn_with_slack(logits if prior is None else logits + prior, self.iterations)
            R_i, r_i = weighted_procrustes(P, moved, y)
            R, r = R_i @ R, (R_i @ r.unsqueeze(-1)).squeeze(-1) + r_i
        return torch.cat([R.flatten(1), r], dim=-1)
