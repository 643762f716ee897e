"""The action table: the one source of truth for the action set (paper, "Experiments").

Each step-size scale contributes 12 actions: rotations of ``±deg`` about x, y, z, then translations
of ``±dist`` along x, y, z. Rotations are applied about the current source centroid and
translations are added (paper, "Application of actions"), so the two kinds stay decoupled.
The default scales are the paper's: (10°, 0.1) then (0.5°, 0.01). A third, finer scale can be
added by passing more scales.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from pranet.core.se3 import Array, axis_rotation

AXES = "xyz"
DEFAULT_SCALES: tuple[tuple[float, float], ...] = ((10.0, 0.1), (0.5, 0.01))
DEFAULT_SCHEDULE: tuple[int, ...] = (20, 40)


@dataclass(frozen=True)
class Action:
    """One discrete action. ``step`` is radians for rotations, input units for translations."""

    kind: str  # "rotation" | "translation"
    axis: int  # 0, 1, 2
    sign: int  # +1 | -1
    step: float
    scale: int  # index of the step-size scale this action belongs to
    name: str


@dataclass(frozen=True)
class ActionTable:
    """An ordered set of actions grouped by step-size scale.

    ``scales[i] = (rotation_deg, translation)``; the actions of scale ``i`` are
    ``indices_of_scale(i)``. Network outputs follow this order.
    """

    scales: tuple[tuple[float, float], ...]

    @cached_property
    def actions(self) -> tuple[Action, ...]:
        out: list[Action] = []
        for s, (deg, dist) in enumerate(self.scales):
            for axis in range(3):
                for sign in (1, -1):
                    out.append(
                        Action(
                            "rotation", axis, sign, np.deg2rad(deg), s, f"rot{'+-'[sign < 0]}{AXES[axis]}:{deg:g}deg"
                        )
                    )
            for axis in range(3):
                for sign in (1, -1):
                    out.append(
                        Action("translation", axis, sign, dist, s, f"trans{'+-'[sign < 0]}{AXES[axis]}:{dist:g}")
                    )
        return tuple(out)

    def __len__(self) -> int:
        return len(self.actions)

    @cached_property
    def names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.actions)

    @cached_property
    def rotations(self) -> Array:
        """``(A, 3, 3)``: the rotation of each action (identity for translations)."""
        return np.stack(
            [axis_rotation(a.axis, a.sign * a.step) if a.kind == "rotation" else np.eye(3) for a in self.actions]
        )

    @cached_property
    def translations(self) -> Array:
        """``(A, 3)``: the translation of each action (zero for rotations)."""
        t = np.zeros((len(self.actions), 3))
        for i, a in enumerate(self.actions):
            if a.kind == "translation":
                t[i, a.axis] = a.sign * a.step
        return t

    @cached_property
    def is_rotation(self) -> np.ndarray:
        return np.array([a.kind == "rotation" for a in self.actions])

    @cached_property
    def scale_index(self) -> np.ndarray:
        """``(A,)``: the scale of each action."""
        return np.array([a.scale for a in self.actions])

    @cached_property
    def scale_members(self) -> np.ndarray:
        """``(A, S)`` float: 1 where action ``a`` belongs to scale ``s`` (per-scale sums as one product)."""
        return (self.scale_index[:, None] == np.arange(len(self.scales))).astype(np.float64)

    def indices_of_scale(self, scale: int) -> np.ndarray:
        return np.flatnonzero(self.scale_index == scale)

    @cached_property
    def rotation_indices(self) -> np.ndarray:
        return np.flatnonzero(self.is_rotation)

    @cached_property
    def translation_indices(self) -> np.ndarray:
        return np.flatnonzero(~self.is_rotation)

    def to_json(self) -> str:
        return json.dumps({"scales": [list(s) for s in self.scales], "actions": list(self.names)}, sort_keys=True)

    @cached_property
    def fingerprint(self) -> str:
        """sha256 of the canonical JSON of the table: stored in the ONNX metadata, checked at load."""
        return hashlib.sha256(self.to_json().encode()).hexdigest()


def build_action_table(scales: Sequence[Sequence[float]] = DEFAULT_SCALES) -> ActionTable:
    """``scales``: ``[(rotation_deg, translation), ...]``, coarse to fine."""
    if not scales:
        raise ValueError("at least one step-size scale is required")
    return ActionTable(tuple((float(d), float(t)) for d, t in scales))
