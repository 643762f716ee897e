"""Training configuration and presets. Resolved once at the CLI edge and passed in explicitly."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from typing import Any

from pranet.core.actions import DEFAULT_SCALES, DEFAULT_SCHEDULE
from pranet.model.config import CPU_NET, PAPER_NET, NetConfig


@dataclass(frozen=True)
class SamplingConfig:
    """Training states. ``full`` components are ``(max_angle_deg, max_translation, weight)``.

    ``visited``, when above 0, is the fraction of batches moved first by the current network's own greedy coarse
    steps (``training.visited``): the states the policy reaches, labelled with the truth.

    ``near_settings``, when given, replaces ``settings`` for the states drawn from a component of at most
    ``near_max_deg``: a setting can be weighted where the agent finishes without starving the far-off states
    of the others (docs/DESIGN.md, "A 1:1:1 finish, and the partial weight near the truth only").
    """

    settings: tuple[tuple[str, float], ...] = (("clean", 1.0),)
    near_settings: tuple[tuple[str, float], ...] = ()
    near_max_deg: float = 10.0
    rotation: str = "isotropic"  # "isotropic" | "naive" (then angles are per Euler axis)
    full: tuple[tuple[float, float, float], ...] = ((60.0, 0.5, 1.0),)
    curriculum: str = "paper"  # "paper" | "uniform" | "adhoc"
    curriculum_fraction: float = 70 / 1300
    small: tuple[float, float] = (10.0, 0.5 / 7)
    orientation_max_deg: float = 0.0
    reward: str = "se3"  # "se3" | "l2" | "mcd"
    # On-policy states (training.visited): this fraction of the batches is moved by 1..visited_steps greedy coarse
    # steps of the network being trained before its loss is taken.
    visited: float = 0.0
    visited_steps: int = 20


@dataclass(frozen=True)
class OptimConfig:
    optimizer: str = "sgd"  # "sgd" | "adamw"
    lr: float = 0.1
    momentum: float = 0.9
    weight_decay: float = 1e-4
    schedule: str = "step"  # "step" (milestones) | "cosine"
    milestones: tuple[int, ...] = (300, 700, 1000)
    gamma: float = 0.1
    batch_size: int = 32
    epochs: int = 1300
    grad_clip: float = 0.0
    reward_weight: float = 1.0  # the paper's reward MSE
    pose_weight: float = 0.0  # analytic networks: the estimated residual pose against the true one
    pose_loss: str = "absolute"  # "absolute" (RPMNet: mean point distance) | "relative" (÷ the state's own size)
    overlap_weight: float = 0.0  # networks with an overlap head: binary cross-entropy against the true overlap


@dataclass(frozen=True)
class TrainConfig:
    preset: str
    net: NetConfig
    sampling: SamplingConfig
    optim: OptimConfig
    scales: tuple[tuple[float, float], ...] = DEFAULT_SCALES
    schedule: tuple[int, ...] = DEFAULT_SCHEDULE
    seed: int = 1234
    split_seed: int = 1234
    val_fraction: float = 0.1
    val_samples: int = 512
    threads: int = 0  # torch intra-op threads; 0 = torch's default
    init: str = ""  # warm start: a checkpoint whose matching parameters are copied before epoch 0
    notes: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        s = d["sampling"]
        sampling = SamplingConfig(
            **{
                **s,
                "settings": tuple(tuple(x) for x in s["settings"]),
                "near_settings": tuple(tuple(x) for x in s.get("near_settings", ())),
                "full": tuple(tuple(x) for x in s["full"]),
                "small": tuple(s["small"]),
            }
        )
        o = d["optim"]
        optim = OptimConfig(**{**o, "milestones": tuple(o["milestones"])})
        rest = {k: v for k, v in d.items() if k not in ("net", "sampling", "optim")}
        rest["scales"] = tuple(tuple(x) for x in rest["scales"])
        rest["schedule"] = tuple(rest["schedule"])
        return cls(net=NetConfig.from_dict(d["net"]), sampling=sampling, optim=optim, **rest)


PRESETS: dict[str, TrainConfig] = {
    # The paper's numbers ("Parameters", "Clean Dataset"): i.i.d. isotropic samples, curriculum 70/1300.
    "paper": TrainConfig(preset="paper", net=PAPER_NET, sampling=SamplingConfig(), optim=OptimConfig()),
    # The shipped default, sized for a 2-core CPU (see docs/DESIGN.md for the measurements behind it).
    "cpu": TrainConfig(
        preset="cpu",
        net=replace(CPU_NET, n_points=256, pool="maxmean", correspondence=True),
        sampling=SamplingConfig(
            settings=(("clean", 1.0), ("noisy", 1.0), ("partial", 1.0)),
            # Beyond the paper: Haar sampling up to 60° almost never draws the < 10° states the fine
            # phase acts in (0.5 % of samples), so half the samples come from small-error components.
            full=((60.0, 0.5, 0.5), (10.0, 0.1, 0.25), (2.0, 0.02, 0.25)),
            orientation_max_deg=60.0,
        ),
        optim=OptimConfig(
            optimizer="adamw", lr=1e-3, weight_decay=1e-4, schedule="cosine", batch_size=16, epochs=50, grad_clip=1.0
        ),
        threads=2,
    ),
}
# Model 2.0.0 (issue 12): the cpu preset's embedding, warm-started from its run, matched by Sinkhorn with
# slack and scored by the analytic reward layer; trained on the pose error (docs/DESIGN.md, "The agent").
PRESETS["agent"] = replace(
    PRESETS["cpu"],
    preset="agent",
    net=replace(PRESETS["cpu"].net, matching="sinkhorn", reward_head="analytic", match_passes=3),
    optim=replace(PRESETS["cpu"].optim, reward_weight=0.0, pose_weight=1.0, epochs=8),
    init="runs/cpu/best.pt",
)


def parse_override(cfg: TrainConfig, item: str) -> TrainConfig:
    """Apply ``section.key=json`` (or ``key=json``) to ``cfg``, e.g. ``optim.epochs=5``."""
    key, _, raw = item.partition("=")
    if not raw:
        raise ValueError(f"override {item!r} must look like section.key=value")
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    d = cfg.to_dict()
    node = d
    *parents, leaf = key.split(".")
    for p in parents:
        if p not in node or not isinstance(node[p], dict):
            raise ValueError(f"unknown config section {p!r} in {item!r}")
        node = node[p]
    if leaf not in node:
        raise ValueError(f"unknown config key {key!r}")
    node[leaf] = value
    return TrainConfig.from_dict(d)
