"""The real-scan pairs of ``pranet-bench scans``: the pairs file, the right/wrong thresholds and the errors.

The pairs file is a CSV with a header (the format of ``shared/data/scans/pairs.csv``, described in its
``SOURCES.md``): ``id``, ``source``, ``target`` (paths relative to the CSV's folder), ``T_target_source``
(16 numbers, row-major, ``p_target = T @ [p_source; 1]``), ``overlap`` and ``rotation_deg`` (may be empty) and
``kind`` (free text, e.g. ``object range scans (m)``).

Right or wrong: a pair whose ``kind`` contains "object" (any case) is an object pair, judged within 2° and
3 mm; every other pair is a scene, judged within 15° and 30 cm (3DMatch's registration recall thresholds).
Translations are in the clouds' own units and these defaults assume metres; ``--thresholds`` overrides them.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pranet.core.metrics import isotropic_errors
from pranet.core.se3 import Array

COLUMNS = ("id", "source", "target", "T_target_source", "overlap", "rotation_deg", "kind")
RIGID_TOLERANCE = 1e-3  # |R^T R - I| and |det R - 1|: ground truths stored as float32 (3DMatch's) are off by 1e-4


@dataclass(frozen=True)
class Thresholds:
    rotation_deg: float
    translation: float  # the clouds' units


OBJECT = Thresholds(2.0, 0.003)
SCENE = Thresholds(15.0, 0.30)
DEFAULT_THRESHOLDS = {"object": OBJECT, "scene": SCENE}


@dataclass(frozen=True)
class ScanPair:
    id: str
    source: Path
    target: Path
    T_gt: Array  # (4, 4) T_target_source
    overlap: float | None
    rotation_deg: float | None
    kind: str

    @property
    def category(self) -> str:
        """``"object"`` or ``"scene"``: which thresholds judge this pair."""
        return pair_category(self.kind)


def pair_category(kind: str) -> str:
    return "object" if "object" in kind.lower() else "scene"


def thresholds_for(kind: str, table: dict[str, Thresholds] = DEFAULT_THRESHOLDS) -> Thresholds:
    return table[pair_category(kind)]


def parse_thresholds(specs: list[str]) -> dict[str, Thresholds]:
    """``["2,0.003"]`` (every pair) or ``["object=2,0.003", "scene=15,0.3"]`` (per category) over the defaults."""
    table = dict(DEFAULT_THRESHOLDS)
    for spec in specs:
        name, _, values = spec.rpartition("=")
        names = [name] if name else list(table)
        parts = values.split(",")
        if any(n not in table for n in names) or len(parts) != 2:
            raise ValueError(f"--thresholds {spec!r}: expected ROT_DEG,TRANSLATION, optionally after object= or scene=")
        try:
            rot, trans = float(parts[0]), float(parts[1])
        except ValueError:
            raise ValueError(f"--thresholds {spec!r}: the two values must be numbers") from None
        if not (rot > 0 and trans > 0 and math.isfinite(rot) and math.isfinite(trans)):
            raise ValueError(f"--thresholds {spec!r}: both values must be positive and finite")
        for n in names:
            table[n] = Thresholds(rot, trans)
    return table


def _optional_float(text: str, where: str) -> float | None:
    if not text.strip():
        return None
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"{where}: {text!r} is not a number") from None


def parse_transform(text: str, where: str) -> Array:
    """16 numbers (row-major) -> a rigid 4x4 ``T``, or ``ValueError`` naming ``where``."""
    try:
        values = [float(x) for x in text.split()]
    except ValueError:
        raise ValueError(f"{where}: T_target_source must be 16 numbers separated by spaces") from None
    if len(values) != 16:
        raise ValueError(f"{where}: T_target_source has {len(values)} numbers, expected 16 (row-major 4x4)")
    T = np.array(values, dtype=np.float64).reshape(4, 4)
    R = T[:3, :3]
    if (
        not np.isfinite(T).all()
        or not np.allclose(T[3], [0, 0, 0, 1])
        or np.abs(R.T @ R - np.eye(3)).max() > RIGID_TOLERANCE
        or abs(np.linalg.det(R) - 1.0) > RIGID_TOLERANCE
    ):
        raise ValueError(f"{where}: T_target_source is not a rigid transform (rotation, translation, last row 0 0 0 1)")
    return T


def read_pairs(csv_path: str | Path) -> list[ScanPair]:
    """The pairs of ``csv_path``, their cloud paths resolved against its folder; ``ValueError`` on a malformed
    file, a missing column or cloud, or a repeated id."""
    csv_path = Path(csv_path)
    if not csv_path.is_file():
        raise ValueError(f"{csv_path}: no such pairs file")
    with open(csv_path, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        missing = [c for c in COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{csv_path}: missing column(s) {', '.join(missing)} (expected {', '.join(COLUMNS)})")
        rows = list(reader)
    pairs: list[ScanPair] = []
    for line, row in enumerate(rows, start=2):
        where = f"{csv_path}:{line} ({row['id']})"
        clouds = [csv_path.parent / row[c] for c in ("source", "target")]
        for path in clouds:
            if not path.is_file():
                raise ValueError(f"{where}: no such cloud {path}")
        pairs.append(
            ScanPair(
                id=row["id"],
                source=clouds[0],
                target=clouds[1],
                T_gt=parse_transform(row["T_target_source"], where),
                overlap=_optional_float(row["overlap"], where),
                rotation_deg=_optional_float(row["rotation_deg"], where),
                kind=row["kind"],
            )
        )
    ids = [p.id for p in pairs]
    if len(set(ids)) != len(ids):
        raise ValueError(f"{csv_path}: repeated pair id(s) {sorted({i for i in ids if ids.count(i) > 1})}")
    if not pairs:
        raise ValueError(f"{csv_path}: no pairs")
    return pairs


def pose_errors(T_est: Array, T_gt: Array) -> tuple[float, float]:
    """(rotation error in degrees, translation error in the clouds' units) of ``T_est`` against ``T_gt``: the
    angle of ``R_gtᵀ R_est`` and ``|t_est - t_gt|`` (3DMatch's definitions; ``core.metrics.isotropic_errors``)."""
    return isotropic_errors(T_est, T_gt)


def is_right(rotation_deg: float, translation: float, limits: Thresholds) -> bool:
    return bool(rotation_deg < limits.rotation_deg and translation < limits.translation)
