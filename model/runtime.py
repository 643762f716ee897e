"""The reward network in onnxruntime (no torch): what the service and the evaluation run.

``RewardModel.load(model_dir)`` checks the model card, the sha256 of both graphs and the action
table fingerprint against this package's action table, then opens two CPU sessions with explicit
thread settings. ``model.score_fn(target)`` embeds the target once and returns the
``score_fn(source, target) -> rewards`` the agent loop calls; it computes the source kNN graph on
its first call and reuses it (rigid motion does not change it).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from pranet.core.actions import ActionTable, build_action_table
from pranet.core.agent import ScoreFn
from pranet.core.knn import knn_indices

GRAPHS = ("embed.onnx", "score.onnx")


class ModelLoadError(RuntimeError):
    """The model directory is missing, corrupt or does not match this package's action table."""


def default_model_dir() -> Path:
    """The model shipped inside the package."""
    return Path(str(resources.files("pranet.model") / "default"))


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def read_card(model_dir: Path, verify: bool = True) -> dict[str, Any]:
    card_path = model_dir / "card.json"
    if not card_path.is_file():
        raise ModelLoadError(
            f"no model card at {card_path}: is {model_dir} a model directory written by pranet-export?"
        )
    try:
        card = json.loads(card_path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ModelLoadError(f"unreadable model card {card_path}: {e}") from e
    for name in GRAPHS:
        path = model_dir / name
        if not path.is_file():
            raise ModelLoadError(f"missing model graph {path}")
        if verify and _sha256(path) != card.get("files", {}).get(name):
            raise ModelLoadError(f"{path}: sha256 does not match the model card (corrupt or replaced file)")
    table = build_action_table(card["actions"]["scales"])
    if table.fingerprint != card["actions"]["fingerprint"]:
        raise ModelLoadError(
            f"action table mismatch: the model was trained with fingerprint {card['actions']['fingerprint'][:12]}, "
            f"this package builds {table.fingerprint[:12]} from the same scales"
        )
    return card


@dataclass
class RewardModel:
    card: dict[str, Any]
    table: ActionTable
    schedule: tuple[int, ...]
    n_points: int
    k: int
    sha256: str
    _embed: Any
    _score: Any
    _score_inputs: tuple[str, ...] = ()

    @classmethod
    def load(
        cls, model_dir: str | Path | None = None, threads: int = 2, verify: bool = True, optimization: str = "all"
    ) -> RewardModel:
        import onnxruntime as ort

        model_dir = Path(model_dir) if model_dir else default_model_dir()
        card = read_card(model_dir, verify=verify)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = {
            "none": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
            "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
            "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
            "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
        }[optimization]
        try:
            sessions = [
                ort.InferenceSession(str(model_dir / g), sess_options=opts, providers=["CPUExecutionProvider"])
                for g in GRAPHS
            ]
        except Exception as e:  # onnxruntime raises its own exception types for bad files
            raise ModelLoadError(f"onnxruntime cannot load {model_dir}: {e}") from e
        digest = hashlib.sha256("".join(card["files"][g] for g in GRAPHS).encode()).hexdigest()
        return cls(
            card=card,
            table=build_action_table(card["actions"]["scales"]),
            schedule=tuple(card["schedule"]),
            n_points=int(card["n_points"]),
            k=int(card["k"]),
            sha256=digest,
            _embed=sessions[0],
            _score=sessions[1],
            _score_inputs=tuple(i.name for i in sessions[1].get_inputs()),
        )

    def embed(self, points: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``points: ([B,] N, 3)`` -> ``(features (B, N, D), centroid (B, 3), knn (B, N, k))``."""
        p = np.asarray(points, dtype=np.float32)
        if p.ndim == 2:
            p = p[None]
        knn = knn_indices(p, self.k)
        feats, cen = self._embed.run(None, {"points": p, "knn": knn})
        return feats, cen, knn

    def score(
        self,
        points: np.ndarray,
        knn: np.ndarray,
        target_points: np.ndarray,
        target_features: np.ndarray,
        target_centroid: np.ndarray,
    ) -> np.ndarray:
        """Batched rewards ``(B, A)``: ``points (B, N, 3) float32``, ``knn (B, N, k) int64``, target ``(B, M, ...)``."""
        feeds = {
            "points": points,
            "knn": knn,
            "target_points": target_points,
            "target_features": target_features,
            "target_centroid": target_centroid,
        }
        return self._score.run(None, {name: feeds[name] for name in self._score_inputs})[0]

    def score_fn(self, target: npt.ArrayLike) -> ScoreFn:
        """A ``score_fn`` for one registration onto ``target: (M, 3)`` (embedded here, once)."""
        t_pts = np.asarray(target, dtype=np.float32)[None]
        t_feat, t_cen, _ = self.embed(t_pts)
        cache: dict[str, np.ndarray] = {}

        def score(source: np.ndarray, _target: np.ndarray) -> np.ndarray:
            pts = np.asarray(source, dtype=np.float32)[None]
            if "knn" not in cache:
                cache["knn"] = knn_indices(pts, self.k)
            return self.score(pts, cache["knn"], t_pts, t_feat, t_cen)[0]

        return score

    def info(self) -> dict[str, Any]:
        return {"name": self.card.get("name"), "version": self.card.get("version"), "sha256": self.sha256}
