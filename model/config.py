"""Network configuration (no torch import: the service reads it from the model card)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

# One round of matching at inference: (the trained round whose predicted (β, γ, α) it uses, a factor on its γ).
MatchingRound = tuple[int, float]

# The fine phase's matching (``score_fine.onnx``): the position-led trained rounds 1 and 2, then round 2 with its
# distance kernel 2× and 4× narrower (γ × 4, × 16), in the clouds' actual placement rather than each about its own
# centroid. Near alignment the feature-led round 0 pulls a partial pair ~10° off and own-centroid coordinates start the
# matching 0.1-0.2 from where the agent has put the source; the paper's agent with this fine phase: partial -3.2 ±
# 0.8°, noisy -0.8° on 100 validation pairs (docs/DESIGN.md, "A fine-phase call").
FINE_ROUNDS: tuple[MatchingRound, ...] = ((1, 1.0), (2, 1.0), (2, 4.0), (2, 16.0))


def parse_rounds(spec: str) -> tuple[MatchingRound, ...]:
    """``"1+2+2g4"`` -> ``((1, 1.0), (2, 1.0), (2, 4.0))``: a trained round's index, ``gN`` for γ × N."""
    rounds = []
    for item in spec.split("+"):
        index, _, scale = item.partition("g")
        try:
            rounds.append((int(index), float(scale) if scale else 1.0))
        except ValueError:
            raise ValueError(f"bad matching round {item!r} in {spec!r}: an index, optionally gN (γ × N)") from None
    if any(i < 0 or g <= 0 for i, g in rounds):
        raise ValueError(f"bad matching rounds {spec!r}: indices >= 0, γ factors > 0")
    return tuple(rounds)


def format_rounds(rounds: tuple[MatchingRound, ...]) -> str:
    """The inverse of ``parse_rounds``."""
    return "+".join(f"{i}" if g == 1.0 else f"{i}g{g:g}" for i, g in rounds)


@dataclass(frozen=True)
class NetConfig:
    """The reward network (paper, "Architecture").

    ``edge_widths``: EdgeConv output widths. With ``project``, the concatenation of all EdgeConv
    outputs is mapped point-wise to ``emb_dim`` (DGCNN's last layer); without it, the last EdgeConv
    width is the embedding. ``graph``: ``"static"`` (kNN in xyz, computed once per cloud and reused)
    or ``"dynamic"`` (kNN recomputed in feature space at each layer, as in DGCNN).
    ``center_inputs``: embed each cloud about its own centroid and give the heads the centroid
    offset, so the point features do not depend on translation.
    ``correspondence`` (beyond the paper): soft correspondences of the source points in the target
    from the final features (DCP-style attention over target xyz), reduced to a rotation estimate
    (polar factor of the cross-covariance, by Newton-Schulz) and a residual offset that join the
    pooled features at the MLP input.
    ``matching`` (with ``correspondence``): ``"softmax"`` (DCP: every source point onto a soft target
    point) or ``"sinkhorn"`` (RPMNet: a doubly-normalised assignment with a slack row and column, so
    points without a counterpart drop out; affinity from the features and from the current xyz
    distances, with the sharpness predicted from the pooled features), then a weighted Procrustes.
    ``reward_head``: ``"mlp"`` (the paper's MLP heads) or ``"analytic"``: the 24 rewards computed in
    closed form from the estimated residual pose, exactly as ``core.reward.true_rewards`` computes the
    labels from the true one; needs ``matching="sinkhorn"`` and ``center_inputs``.
    """

    n_points: int = 512
    k: int = 16
    edge_widths: tuple[int, ...] = (64, 64, 128)
    project: bool = True
    emb_dim: int = 128
    graph: str = "static"
    heads: int = 4
    blocks: int = 1
    self_attention: bool = False
    ff_dim: int = 256
    pool: str = "max"  # "max" | "maxmean"
    center_inputs: bool = True
    correspondence: bool = False
    mlp_shared: tuple[int, ...] = (256,)
    mlp_head: tuple[int, ...] = (128,)
    matching: str = "softmax"  # "softmax" | "sinkhorn"
    sinkhorn_iters: int = 5
    match_passes: int = 1  # sinkhorn: rounds of matching, each from the previous round's estimate
    # sinkhorn: rounds at inference (0: ``match_passes``); those beyond the trained ones reuse the last trained
    # round's (β, γ, α), as RPMNet trains with 2 iterations and tests with 5 (docs/DESIGN.md, "More matching rounds
    # at inference"). Set at export (``pranet-export --match-passes``), never in training.
    inference_passes: int = 0
    reward_head: str = "mlp"  # "mlp" | "analytic"
    # sinkhorn: a score per point, from its cross-attended features, of having a counterpart in the other cloud
    # (PREDATOR's and OMNet's overlap masks); its log-sigmoid lowers the point's matching logits, so points of a
    # cropped-away part go to the slack. Trained with ``OptimConfig.overlap_weight`` (docs/DESIGN.md, "An overlap
    # head").
    overlap_head: bool = False
    # RPMNet's point-pair features (a distance and three normal angles per graph edge, normals estimated from the
    # kNN graph) added to the first EdgeConv: they do not change with the pose or with the crop's centroid, where the
    # xyz features do (docs/DESIGN.md, "Point-pair features").
    point_pair_features: bool = False
    # The first EdgeConv sees only each point's offsets to its neighbours, not its position about the centroid, so
    # one surface point gets the same first features in two crops whose centroids differ (docs/DESIGN.md, "Local
    # first-layer features").
    local_edges: bool = False

    def __post_init__(self) -> None:
        if self.matching not in ("softmax", "sinkhorn"):
            raise ValueError(f"unknown matching {self.matching!r}")
        if self.inference_passes < 0:
            raise ValueError(f"inference_passes must be >= 0, got {self.inference_passes}")
        if self.reward_head not in ("mlp", "analytic"):
            raise ValueError(f"unknown reward_head {self.reward_head!r}")
        if self.reward_head == "analytic" and not (
            self.correspondence and self.matching == "sinkhorn" and self.center_inputs
        ):
            raise ValueError("reward_head='analytic' needs correspondence, matching='sinkhorn' and center_inputs")

        if self.overlap_head and self.matching != "sinkhorn":
            raise ValueError("overlap_head needs matching='sinkhorn'")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> NetConfig:
        d = dict(d)
        for key in ("edge_widths", "mlp_shared", "mlp_head"):
            if key in d:
                d[key] = tuple(d[key])
        return cls(**d)


PAPER_NET = NetConfig(
    n_points=1024,
    k=20,
    edge_widths=(64, 64, 128, 256, 1024),
    project=False,
    emb_dim=1024,
    graph="dynamic",
    heads=4,
    blocks=1,
    self_attention=True,
    ff_dim=1024,
    pool="max",
    center_inputs=False,
    mlp_shared=(512,),
    mlp_head=(256,),
)

CPU_NET = NetConfig()
