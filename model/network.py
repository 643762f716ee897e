"""The PRANet reward network in PyTorch (paper, "Architecture", Fig. 2).

DGCNN embedding (shared by source and target; ``model.embedding``) -> Transformer cross-attention -> max-pool -> a
shared MLP -> separate rotation and translation heads, which output one reward per action of the table; or, in the
2.x networks, soft correspondences reduced to a pose (``model.matching``) and the rewards of that pose in closed form.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from pranet.core.actions import ActionTable
from pranet.model.config import MatchingRound, NetConfig
from pranet.model.embedding import DGCNN
from pranet.model.matching import Prepared, SinkhornCorrespondence, SoftCorrespondence


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

    def attend(self, src: Tensor, tgt: Tensor) -> tuple[Tensor, Tensor, list[Tensor]]:
        """Both clouds' embeddings after the Transformer blocks, and their pooled vectors ``[(B, pooled)] * 2``: none
        of it depends on where either cloud is (with ``center_inputs``)."""
        for block in self.blocks:
            # Φ_X = F_X + φ(F_X, F_Y), Φ_Y = F_Y + φ(F_Y, F_X) with shared weights (paper, "Architecture").
            src, tgt = block(src, tgt), block(tgt, src)
        return src, tgt, [self._pool(src), self._pool(tgt)]

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
        fine_rounds: Sequence[MatchingRound] | None = None,
        twin: Tensor | None = None,
    ) -> Tensor:
        """Embeddings of both clouds -> ``(B, P)``: the MLP input except the centroid offset.

        With ``center_inputs`` this does not depend on where the source is, only on its orientation: a
        translation action leaves it unchanged (``head`` alone re-scores), which the runtime exploits.
        ``src_points``/``tgt_points`` (``(B, N, 3)``, ``(B, M, 3)``) are needed with ``correspondence``.
        ``fine_rounds`` (Sinkhorn matching): the fine phase's call. The matching runs these rounds on both clouds
        about the target's centroid, where the agent has put them, rather than each about its own; the pose is
        returned in the same centred convention, and it now depends on where the source is. ``twin`` (Sinkhorn
        matching): ``core.twins``' term, added to the feature similarity.
        """
        src, tgt, parts = self.attend(src, tgt)
        if self.correspondence is not None:
            if src_points is None or tgt_points is None:
                raise ValueError("this network needs the points of both clouds (correspondence=True)")
            x = src_points - src_centroid.unsqueeze(1)
            y = tgt_points - tgt_centroid.unsqueeze(1)
            if isinstance(self.correspondence, SinkhornCorrespondence):
                # Concatenated after x and y, as before the fine call's refactor: score.onnx stays node for node.
                pooled = torch.cat(parts, dim=-1)
                if fine_rounds is None:
                    pose = self.correspondence(src, tgt, x, y, pooled, twin=twin)
                else:
                    offset = src_centroid - tgt_centroid
                    pose = self.placed_pose(src, tgt, x, y, pooled, offset, fine_rounds, twin=twin)
                if self.analytic is not None:
                    return pose  # the analytic head needs nothing else
                parts.append(pose)
            else:
                parts.append(self.correspondence(src, tgt, x, y))
        return torch.cat(parts, dim=-1)

    def placed_pose(
        self,
        src: Tensor | None,
        tgt: Tensor | None,
        x: Tensor,
        y: Tensor,
        pooled: Tensor | None,
        offset: Tensor,
        rounds: Sequence[MatchingRound],
        prepared: Prepared | None = None,
        twin: Tensor | None = None,
    ) -> Tensor:
        """The matching's ``(B, 12)`` pose ``y ≈ R x + r`` (centred clouds ``x``, ``y``; ``offset`` = source − target
        centroid), found by matching ``x + offset`` against ``y``: both about the target's centroid. ``prepared``:
        the matching's tensors of an earlier call on the same shapes (``SinkhornCorrespondence.forward``), which a
        translation leaves as they are; then ``src``, ``tgt`` and ``pooled`` are not read."""
        if not isinstance(self.correspondence, SinkhornCorrespondence):
            raise ValueError("a fine-phase call needs matching='sinkhorn'")
        pose = self.correspondence(src, tgt, x + offset.unsqueeze(1), y, pooled, rounds, prepared, twin)
        R, r_placed = pose[:, :9].reshape(-1, 3, 3), pose[:, 9:12]
        # y ≈ R (x + offset) + r_placed = R x + (r_placed + R offset).
        return torch.cat([pose[:, :9], r_placed + (R @ offset.unsqueeze(-1)).squeeze(-1)], dim=-1)

    def fine_call(
        self,
        src: Tensor,
        src_centroid: Tensor,
        tgt: Tensor,
        tgt_centroid: Tensor,
        src_points: Tensor,
        tgt_points: Tensor,
        rounds: Sequence[MatchingRound],
        twin: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """The fine phase's call on embeddings (analytic Sinkhorn networks without an overlap head) -> ``(pose
        (B, 12), similarity (B, N, M), params (B, passes, 3))``: ``pair_features(..., fine_rounds=rounds)``, and what
        ``MatchGraph`` needs to score the same source translated."""
        pose = self.pair_features(src, src_centroid, tgt, tgt_centroid, src_points, tgt_points, rounds, twin)
        if not isinstance(self.correspondence, SinkhornCorrespondence) or self.correspondence.prepared is None:
            raise ValueError("a fine-phase call needs matching='sinkhorn'")
        similarity, params, prior = self.correspondence.prepared
        if prior is not None:
            raise ValueError("a network with an overlap head has no match-only call")
        return pose, similarity, params

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
    ``fine_rounds``: the fine phase's graph (``score_fine.onnx``; ``RewardNet.pair_features``), whose pair features
    change with a translation. A model exported with twins (the card's ``twin_matching``) has a sixth input,
    ``twin (1 | B, N, M)``: ``core.twins``' term, added to the matching's feature similarity.
    """

    def __init__(self, net: RewardNet, fine_rounds: Sequence[MatchingRound] | None = None) -> None:
        super().__init__()
        self.net = net
        self.fine_rounds = None if fine_rounds is None else tuple(fine_rounds)

    def forward(
        self,
        points: Tensor,
        knn: Tensor,
        target_points: Tensor,
        target_features: Tensor,
        target_centroid: Tensor,
        twin: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        src, centroid = self.net.embed(points, knn)
        pair = self.net.pair_features(
            src, centroid, target_features, target_centroid, points, target_points, self.fine_rounds, twin
        )
        return self.net.head(pair, centroid - target_centroid), pair


class FineScoreGraph(nn.Module):
    """The fine phase's graph (``score_fine.onnx``): ``ScoreGraph(net, rounds)``'s inputs -> ``(rewards,
    pair_features, similarity, match_params)``, the last two what ``MatchGraph`` needs to score the same source
    after a translation (``RewardNet.fine_call``); the returned similarity includes the ``twin`` input's term."""

    def __init__(self, net: RewardNet, rounds: Sequence[MatchingRound]) -> None:
        super().__init__()
        self.net = net
        self.rounds = tuple(rounds)

    def forward(
        self,
        points: Tensor,
        knn: Tensor,
        target_points: Tensor,
        target_features: Tensor,
        target_centroid: Tensor,
        twin: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        src, centroid = self.net.embed(points, knn)
        pair, similarity, params = self.net.fine_call(
            src, centroid, target_features, target_centroid, points, target_points, self.rounds, twin
        )
        return self.net.head(pair, centroid - target_centroid), pair, similarity, params


class MatchGraph(nn.Module):
    """The fine phase's match-only graph (``match_fine.onnx``): ``(points, target_points, target_centroid,
    similarity, match_params) -> rewards``.

    A translation leaves the source's features, the attention, the feature similarity and the rounds' ``(β, γ, α)``
    as they were (``center_inputs``); only the matching rounds, which run on the clouds as placed, see it. So a
    translated source is re-scored from ``FineScoreGraph``'s ``similarity`` and ``match_params`` with the rounds
    alone, with what ``score_fine.onnx`` would return for it.
    """

    def __init__(self, net: RewardNet, rounds: Sequence[MatchingRound]) -> None:
        super().__init__()
        self.net = net
        self.rounds = tuple(rounds)

    def forward(
        self,
        points: Tensor,
        target_points: Tensor,
        target_centroid: Tensor,
        similarity: Tensor,
        match_params: Tensor,
    ) -> Tensor:
        centroid = points.mean(dim=1)  # as RewardNet.embed has it
        x = points - centroid.unsqueeze(1)
        y = target_points - target_centroid.unsqueeze(1)
        offset = centroid - target_centroid
        pair = self.net.placed_pose(None, None, x, y, None, offset, self.rounds, (similarity, match_params, None))
        return self.net.head(pair, offset)


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
