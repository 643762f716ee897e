"""The reward network in onnxruntime (no torch): what the service and the evaluation run.

``RewardModel.load(model_dir)`` checks the model card, the sha256 of its graphs (``embed.onnx``,
``score.onnx`` and, when listed, ``head.onnx``) and the action table fingerprint against this package's
action table, then opens one CPU session per graph with explicit thread settings.
``model.batch_score_fn(target)`` embeds the target once and returns the ``score(sources, target) ->
rewards`` the agent loop calls (``score_fn`` is the same with one source); it computes the source kNN
graph on its first call and reuses it (rigid motion does not change it).

Translation steps: the network embeds each cloud about its own centroid (``center_inputs``), so a
translated source has the same features, attention and soft correspondences; only the centroid offset
fed to the heads changes. ``score.onnx`` also returns those pair features, and when a source's centred
points equal a row of the previous call's (to ``SAME_SHAPE_ATOL``: the last action was a translation),
it is re-scored with ``head.onnx`` (the heads alone, microseconds) instead of the whole network.
The fine phase's call (``score_fine.onnx``) matches the clouds as placed, so a translation changes its soft
correspondences, but not the features, attention, feature similarity or matching parameters it computes them
from: it returns those, and ``match_fine.onnx`` re-runs only the matching rounds for a translated source.
For a network with the analytic reward layer, the score function's ``pose`` gives the estimated residual pose
itself (``core.agent``'s walk), from the same call.
The rewards agree with a full call to float32 rounding (``tests/model/test_export_runtime.py``). Model
directories without ``head.onnx`` (exported before it) run every step through ``score.onnx``.

``precision="int8"`` loads the ``*.int8.onnx`` graphs (``pranet.model.quantize``, written by
``pranet-export --int8``) instead of the fp32 graphs; their sha256 is checked against the card the
same way. The session options are measured in ``docs/PERFORMANCE.md`` (``pranet-bench``).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from pranet.core.actions import ActionTable, build_action_table
from pranet.core.agent import BatchScoreFn, ScoreFn
from pranet.core.knn import knn_indices
from pranet.core.twins import twin_similarity

GRAPHS = ("embed.onnx", "score.onnx")  # required
HEAD_GRAPH = "head.onnx"  # optional: the MLP heads alone, for translation steps
PRECISIONS = ("fp32", "int8")
INT8_GRAPHS = ("embed.int8.onnx", "score.int8.onnx")
HEAD_INT8_GRAPH = "head.int8.onnx"
# Optional: the fine phase's network call (``model.config.FINE_ROUNDS``), matching in the clouds' actual placement;
# the card's ``fine_matching`` names its rounds.
FINE_GRAPH = "score_fine.onnx"
FINE_INT8_GRAPH = "score_fine.int8.onnx"
# Optional: the fine call's matching rounds alone, which re-score a translated source from the last fine call's
# cached similarity. It has no learned weights of its own to quantize, so both precisions run it.
FINE_MATCH_GRAPH = "match_fine.onnx"
OPTIMIZATION_LEVELS = ("none", "basic", "extended", "all")
EXECUTION_MODES = ("sequential", "parallel")
# Centred source points within this (unit frame) of the previous call's: the same orientation, so the
# pair features are reused. A 0.5° turn moves a cloud of radius 1e-3 by 9e-6, well above it.
SAME_SHAPE_ATOL = 1e-6


def graph_files(precision: str = "fp32") -> tuple[str, str]:
    """``(embed, score)`` file names of ``precision``."""
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}; choose from {PRECISIONS}")
    return GRAPHS if precision == "fp32" else INT8_GRAPHS


def head_file(precision: str = "fp32") -> str:
    """The head graph's file name of ``precision``."""
    graph_files(precision)  # validates precision
    return HEAD_GRAPH if precision == "fp32" else HEAD_INT8_GRAPH


def fine_file(precision: str = "fp32") -> str:
    """The fine-phase score graph's file name of ``precision``."""
    graph_files(precision)  # validates precision
    return FINE_GRAPH if precision == "fp32" else FINE_INT8_GRAPH


def card_graphs(card: dict[str, Any], precision: str = "fp32") -> tuple[str, ...]:
    """The graph files of ``precision`` that ``card`` describes: embed, score and (when listed) the head and the
    fine-phase score graph, then the fine phase's match-only graph (the same file in both precisions)."""
    return quantized_graphs(card, precision) + (
        (FINE_MATCH_GRAPH,) if FINE_MATCH_GRAPH in card.get("files", {}) else ()
    )


def quantized_graphs(card: dict[str, Any], precision: str = "fp32") -> tuple[str, ...]:
    """``card_graphs`` of ``precision`` that have an int8 counterpart (all but the match-only graph)."""
    files = card.get("files", {})
    return (
        graph_files(precision)
        + ((head_file(precision),) if HEAD_GRAPH in files else ())
        + ((fine_file(precision),) if FINE_GRAPH in files else ())
    )


class ModelLoadError(RuntimeError):
    """The model directory is missing, corrupt or does not match this package's action table."""


def default_model_dir() -> Path:
    """The model shipped inside the package."""
    return Path(str(resources.files("pranet.model") / "default"))


def sha256_file(path: str | Path) -> str:
    """The hex sha256 of a file's bytes, read in 1 MiB blocks (model graphs, checkpoints, data files)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_card(model_dir: Path, verify: bool = True, precision: str = "fp32") -> dict[str, Any]:
    card_path = model_dir / "card.json"
    if not card_path.is_file():
        raise ModelLoadError(
            f"no model card at {card_path}: is {model_dir} a model directory written by pranet-export?"
        )
    try:
        card = json.loads(card_path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ModelLoadError(f"unreadable model card {card_path}: {e}") from e
    files = card.get("files", {})
    graphs = card_graphs(card, precision)
    if precision != "fp32":
        missing = [name for name in graphs if name not in files or not (model_dir / name).is_file()]
        made_from = card.get("quantization", {}).get("from", {})
        if missing:
            raise ModelLoadError(
                f"no {precision} graphs in {model_dir} (missing or not in the card: {', '.join(missing)}); "
                f"write them with: pranet-export --int8 --out {model_dir}"
            )
        if any(made_from.get(name) != files.get(name) for name in quantized_graphs(card)):
            raise ModelLoadError(
                f"the {precision} graphs in {model_dir} were made from other fp32 graphs than the card's (stale); "
                f"re-run: pranet-export --int8 --out {model_dir}"
            )
    for name in graphs:
        path = model_dir / name
        if not path.is_file():
            raise ModelLoadError(f"missing model graph {path}")
        if verify and sha256_file(path) != files.get(name):
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
    _head: Any = None  # head.onnx session, or None: every step runs score.onnx
    _fine: Any = None  # score_fine.onnx session, or None: the model has no fine-phase call
    _match: Any = None  # match_fine.onnx session, or None: every fine step runs score_fine.onnx

    precision: str = "fp32"
    reuse_translations: bool = True  # re-score translated sources with the head alone (when _head exists)
    use_twins: bool = True  # feed core.twins' term to a graph that takes it (False: zeros, the call without it)

    @classmethod
    def load(
        cls,
        model_dir: str | Path | None = None,
        threads: int = 2,
        verify: bool = True,
        optimization: str = "all",
        precision: str = "fp32",
        execution: str = "sequential",
        arena: bool = True,
        mem_pattern: bool = True,
        spinning: bool = False,
        reuse_translations: bool = True,
        use_twins: bool = True,
    ) -> RewardModel:
        """Open the graphs of ``precision`` in CPU sessions built by ``session_options`` (same arguments).

        ``reuse_translations``: re-score a translated source with ``head.onnx`` (when the model has it
        and embeds centred clouds); ``False`` runs ``score.onnx`` at every step. ``use_twins=False``: a model whose
        graphs take the twin term (``twins``) is fed zeros for it, which is the call without the term.
        """
        model_dir = Path(model_dir) if model_dir else default_model_dir()
        card = read_card(model_dir, verify=verify, precision=precision)
        # The head re-scores translated sources only when the embedding ignores where a cloud is.
        has_head = HEAD_GRAPH in card.get("files", {}) and bool(card.get("net", {}).get("center_inputs"))
        listed = card_graphs(card, precision)
        graphs = [g for g in listed if has_head or g != head_file(precision)]
        opts = session_options(threads, optimization, execution, arena, mem_pattern, spinning)
        try:
            import onnxruntime as ort

            sessions = {
                g: ort.InferenceSession(str(model_dir / g), sess_options=opts, providers=["CPUExecutionProvider"])
                for g in graphs
            }
        except Exception as e:  # onnxruntime raises its own exception types for bad files
            raise ModelLoadError(f"onnxruntime cannot load {model_dir}: {e}") from e
        # The model's identity: the graphs every registration runs (the fine-phase graphs added to a model directory
        # leave it as it was).
        core = [g for g in graphs if g not in (fine_file(precision), FINE_MATCH_GRAPH)]
        digest = hashlib.sha256("".join(card["files"][g] for g in core).encode()).hexdigest()
        embed, score = graph_files(precision)
        return cls(
            card=card,
            table=build_action_table(card["actions"]["scales"]),
            schedule=tuple(card["schedule"]),
            n_points=int(card["n_points"]),
            k=int(card["k"]),
            sha256=digest,
            _embed=sessions[embed],
            _score=sessions[score],
            _score_inputs=tuple(i.name for i in sessions[score].get_inputs()),
            _head=sessions.get(head_file(precision)),
            _fine=sessions.get(fine_file(precision)),
            _match=sessions.get(FINE_MATCH_GRAPH),
            precision=precision,
            reuse_translations=reuse_translations,
            use_twins=use_twins,
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
        twin: np.ndarray | None = None,
    ) -> np.ndarray:
        """Batched rewards ``(B, A)``: ``points (B, N, 3) float32``, ``knn (B, N, k) int64``, target ``(B, M, ...)``;
        ``twin (1 | B, N, M)`` for a model with ``twins`` (``core.twins.twin_similarity``)."""
        feeds = {
            "points": points,
            "knn": knn,
            "target_points": target_points,
            "target_features": target_features,
            "target_centroid": target_centroid,
        }
        if twin is not None:
            feeds["twin"] = twin
        elif self.twins is not None:
            raise ValueError("this model's score graph takes the twin term (core.twins): pass twin")
        return self._score.run(["rewards"], {name: feeds[name] for name in self._score_inputs})[0]

    def score_fn(self, target: npt.ArrayLike) -> ScoreFn:
        """A ``score_fn(source (N, 3), target) -> (A,)`` for one registration onto ``target: (M, 3)``: the batched
        function below with one row (the same caching and head-only re-scoring). Counts in ``score.calls``."""
        batched = self.batch_score_fn(target)

        def single(fn: BatchScoreFn) -> ScoreFn:
            def score(source: np.ndarray, _target: np.ndarray) -> np.ndarray:
                return fn(np.asarray(source)[None], _target)[0]

            return score

        score = single(batched)
        score.calls = batched.calls  # type: ignore[attr-defined]
        score.pose = batched.pose  # type: ignore[attr-defined]
        score.fine = None if batched.fine is None else single(batched.fine)  # type: ignore[attr-defined]
        return score

    def batch_score_fn(self, target: npt.ArrayLike) -> BatchScoreFn:
        """A ``batch_score_fn(sources (B, N, 3), target) -> (B, A)`` for one registration onto ``target: (M, 3)``
        (``BatchScorer``). Counts in ``score.calls`` (rows); ``score.pose`` and ``score.fine`` as there."""
        return BatchScorer(self, target)

    @property
    def twins(self) -> dict[str, Any] | None:
        """The card's ``twin_matching`` (``k``, ``sigma``, ``weight``) when the score graphs take the twin term."""
        return self.card.get("twin_matching") if "twin" in self._score_inputs else None

    def twin_term(
        self, points: np.ndarray, knn: np.ndarray, target: np.ndarray, target_knn: np.ndarray
    ) -> np.ndarray | None:
        """The score graphs' ``twin`` input ``(1, N, M)`` for one source and target ``(N, 3)``, ``(M, 3)`` with their
        kNN graphs (``core.twins``, the card's settings; zeros with ``use_twins=False``), or ``None`` for a model
        whose graphs do not take it."""
        twins = self.twins
        if twins is None:
            return None
        if not self.use_twins:
            return np.zeros((1, len(points), len(target)), dtype=np.float32)
        settings = {key: twins[key] for key in ("k", "sigma", "weight")}
        return twin_similarity(points, knn, target, target_knn, **settings)[None]

    @property
    def has_fine_call(self) -> bool:
        """Whether the model has the fine phase's call (``score_fine.onnx``; ``RegistrationConfig.fine_matching``)."""
        return self._fine is not None

    @property
    def has_match_call(self) -> bool:
        """Whether translated sources of the fine phase are re-scored by ``match_fine.onnx`` (when reusing)."""
        return self._match is not None and self.reuse_translations

    @property
    def analytic(self) -> bool:
        """Whether the rewards follow in closed form from an estimated pose (the ``pose`` of ``batch_score_fn``)."""
        return self.card.get("net", {}).get("reward_head") == "analytic"

    def info(self) -> dict[str, Any]:
        return {"name": self.card.get("name"), "version": self.card.get("version"), "sha256": self.sha256}


def session_options(
    threads: int = 2,
    optimization: str = "all",
    execution: str = "sequential",
    arena: bool = True,
    mem_pattern: bool = True,
    spinning: bool = False,
) -> Any:  # onnxruntime.SessionOptions
    """onnxruntime ``SessionOptions`` with explicit settings (the defaults are what the service uses).

    ``threads``: intra-op threads; ``optimization``: one of ``OPTIMIZATION_LEVELS``; ``execution``:
    ``sequential`` or ``parallel`` (then 2 inter-op threads); ``arena``/``mem_pattern``: the CPU memory
    arena and the memory-pattern planner; ``spinning``: whether idle intra-op threads busy-wait
    (off by default: with another process on the cores it made a score call 4× slower at the median and saved
    nothing at the best call; ``docs/PERFORMANCE.md``).
    """
    import onnxruntime as ort

    if optimization not in OPTIMIZATION_LEVELS:
        raise ValueError(f"unknown optimization {optimization!r}; choose from {OPTIMIZATION_LEVELS}")
    if execution not in EXECUTION_MODES:
        raise ValueError(f"unknown execution {execution!r}; choose from {EXECUTION_MODES}")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 2 if execution == "parallel" else 1
    opts.execution_mode = (
        ort.ExecutionMode.ORT_PARALLEL if execution == "parallel" else ort.ExecutionMode.ORT_SEQUENTIAL
    )
    opts.graph_optimization_level = {
        "none": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
        "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
        "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
        "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
    }[optimization]
    opts.enable_cpu_mem_arena = arena
    opts.enable_mem_pattern = mem_pattern
    opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
    return opts


def same_shape_rows(centred: np.ndarray, previous: np.ndarray | None) -> np.ndarray:
    """For each row of ``centred: (B, N, 3)`` (source points about their centroid), the row of ``previous: (B', N,
    3)`` it equals to ``SAME_SHAPE_ATOL`` (only translated since), or -1."""
    if previous is None:
        return np.full(len(centred), -1)
    d = np.abs(centred[:, None] - previous[None]).max(axis=(2, 3))  # (B, B')
    best = d.argmin(axis=1)
    return np.where(d[np.arange(len(centred)), best] <= SAME_SHAPE_ATOL, best, -1)


def scatter(b: int, parts: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """One ``(b, ...)`` array from ``(row indices, values)`` parts that cover its rows between them."""
    out = np.empty((b, *parts[0][1].shape[1:]), dtype=parts[0][1].dtype)
    for rows, values in parts:
        out[rows] = values
    return out


class TranslationReuse:
    """One graph's per-row outputs of its previous call, with the centred source points they came from: a row whose
    centred points equal one of those (only translated since, ``same_shape_rows``) is re-scored from its row's
    outputs by a cheaper graph instead of the full one."""

    def __init__(self) -> None:
        self.centred: np.ndarray | None = None  # (B', N, 3)
        self.kept: dict[str, np.ndarray] = {}  # name -> (B', ...)

    def rewards(
        self,
        pts: np.ndarray,
        full: Callable[[np.ndarray], dict[str, np.ndarray]],
        partial: Callable[[np.ndarray, np.ndarray, dict[str, np.ndarray]], np.ndarray],
    ) -> np.ndarray:
        """``(B, A)`` rewards of ``pts: (B, N, 3)``. ``full(rows)``: the full graph on those rows -> ``"rewards"`` and
        every output to keep; ``partial(rows, centroids (R, 3), kept)``: the cheaper graph's rewards of translated
        rows from their kept outputs."""
        centroids = pts.mean(axis=1, keepdims=True)  # (B, 1, 3)
        centred = pts - centroids
        match = same_shape_rows(centred, self.centred)
        new, old = np.flatnonzero(match < 0), np.flatnonzero(match >= 0)
        parts: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
        if len(new):
            for name, values in full(new).items():
                parts.setdefault(name, []).append((new, values))
        if len(old):
            kept = {name: values[match[old]] for name, values in self.kept.items()}
            parts.setdefault("rewards", []).append((old, partial(old, centroids[old, 0], kept)))
            for name, values in kept.items():
                parts.setdefault(name, []).append((old, values))
        rows = {name: scatter(len(pts), found) for name, found in parts.items()}
        self.centred = centred
        self.kept = {name: values for name, values in rows.items() if name != "rewards"}
        return rows["rewards"]


class BatchScorer:
    """``RewardModel.batch_score_fn``: the scorer of one registration onto ``target: (M, 3)``.

    The target is embedded once and tiled over ``B``; the rows are one source point set in ``B`` poses (the global
    mode's starts), so the kNN graph of the first row serves every row. Called, it scores through ``score.onnx``,
    except a row only translated since the previous call, which ``head.onnx`` re-scores from that call's pair
    features. ``fine`` (``None`` without ``score_fine.onnx``) is the fine phase's scorer on the same target
    embedding: its pair features change with a translation, so a row goes through ``score_fine.onnx`` unless it is
    only translated since the previous fine call and the model has ``match_fine.onnx``, which re-runs the matching
    rounds alone from that call's similarity and parameters. ``pose`` (analytic models, else ``None``): the
    estimated residual pose of each row. ``calls`` counts the rows each graph scored: ``full``, ``head``, ``fine``
    and ``match``.
    """

    def __init__(self, model: RewardModel, target: npt.ArrayLike) -> None:
        self.model = model
        self.t_pts = np.asarray(target, dtype=np.float32)[None]  # (1, M, 3)
        self.t_feat, self.t_cen, self.t_knn = model.embed(self.t_pts)
        self._twin: np.ndarray | None = None  # (1, N, M), with the source's kNN graph (``_tiles``)
        self._tiled: dict[int, tuple[np.ndarray, ...]] = {}  # B -> (knn, target points, features, centroid) tiled
        self._head = model._head if model.reuse_translations else None
        self._match = model._match if model.reuse_translations else None
        self._after_full, self._after_fine = TranslationReuse(), TranslationReuse()
        self.calls = {"full": 0, "head": 0, "fine": 0, "match": 0}
        self.pose = self._pose if model.analytic else None
        self.fine = self._fine_score if model._fine is not None else None

    def __call__(self, sources: np.ndarray, _target: np.ndarray) -> np.ndarray:
        pts = np.ascontiguousarray(sources, dtype=np.float32)  # (B, N, 3)
        if self._head is None:
            return self._run(pts, ["rewards"])[0]
        return self._after_full.rewards(pts, lambda rows: self._full(pts[rows]), self._head_rewards)

    def _full(self, pts: np.ndarray) -> dict[str, np.ndarray]:
        rewards, pair = self._run(pts, ["rewards", "pair_features"])
        return {"rewards": rewards, "pair": pair}

    def _head_rewards(self, rows: np.ndarray, centroids: np.ndarray, kept: dict[str, np.ndarray]) -> np.ndarray:
        self.calls["head"] += len(rows)
        return self._head.run(None, {"pair_features": kept["pair"], "offset": centroids - self.t_cen})[0]

    def _fine_score(self, sources: np.ndarray, _target: np.ndarray) -> np.ndarray:
        pts = np.ascontiguousarray(sources, dtype=np.float32)
        if self._match is None:
            return self._run(pts, ["rewards"], fine=True)[0]

        def full(rows: np.ndarray) -> dict[str, np.ndarray]:
            names = ["rewards", "similarity", "match_params"]
            return dict(zip(names, self._run(pts[rows], names, fine=True), strict=True))

        def translated(rows: np.ndarray, _centroids: np.ndarray, kept: dict[str, np.ndarray]) -> np.ndarray:
            # Only translated since the last fine call: the same similarity and (β, γ, α), a new placement.
            _, tp, _, tc = self._tiles(len(rows), pts)
            self.calls["match"] += len(rows)
            feeds = {"points": pts[rows], "target_points": tp, "target_centroid": tc, **kept}
            return self._match.run(["rewards"], feeds)[0]

        return self._after_fine.rewards(pts, full, translated)

    def _pose(self, sources: np.ndarray, _target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # The analytic layer's input (``RewardNet.residual_pose``): y ≈ R x + r in centred coordinates, so the source
        # centroid must move by r - (source centroid - target centroid).
        pts = np.ascontiguousarray(sources, dtype=np.float32)
        pair = self._run(pts, ["pair_features"])[0].astype(np.float64)  # (B, 12)
        offset = pts.mean(axis=1, dtype=np.float64) - self.t_cen.astype(np.float64)
        return pair[:, :9].reshape(-1, 3, 3), pair[:, 9:12] - offset

    def _tiles(self, b: int, pts: np.ndarray) -> tuple[np.ndarray, ...]:
        """The source kNN graph (of ``pts``' first row, the first time) and the target's inputs, tiled to ``b``."""
        if b not in self._tiled:
            tiled = self._tiled
            knn = tiled[next(iter(tiled))][0][:1] if tiled else knn_indices(pts[:1], self.model.k)  # (1, N, k)
            tiled[b] = tuple(np.repeat(a, b, axis=0) for a in (knn, self.t_pts, self.t_feat, self.t_cen))
            if self._twin is None:  # pose-blind: one term serves every row and every step of the registration
                self._twin = self.model.twin_term(pts[0], knn[0], self.t_pts[0], self.t_knn[0])
        return self._tiled[b]

    def _run(self, pts: np.ndarray, names: list[str], fine: bool = False) -> list[np.ndarray]:
        """``score.onnx`` (or ``score_fine.onnx``) on the rows ``pts``, counted."""
        knn, tp, tf, tc = self._tiles(len(pts), pts)
        feeds = {"points": pts, "knn": knn, "target_points": tp, "target_features": tf, "target_centroid": tc}
        if self._twin is not None:
            feeds["twin"] = self._twin
        self.calls["fine" if fine else "full"] += len(pts)
        session = self.model._fine if fine else self.model._score
        return session.run(names, {name: feeds[name] for name in self.model._score_inputs})
