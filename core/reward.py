"""The reward (paper, Eq. 1): ``r_a(T) = D(T, 1) - D(a ⊕ T, 1)``, ``D = ||t|| + arccos((tr R - 1) / 2)``.

The state is the residual error of the current source against the target, decoupled about the
current source centroid ``c`` (paper, "Application of actions"):

- ``R_err: (3, 3)``: the rotation still to apply about ``c`` to align the source with the target;
- ``t_err: (3,)``: where ``c`` must go, minus where it is.

A rotation action ``R_a`` about ``c`` gives ``R_err' = R_err @ R_a.T`` and leaves ``t_err``; a
translation action ``t_a`` gives ``t_err' = t_err - t_a`` and leaves ``R_err``. Rewards are
normalised to unit L2 norm separately for each step-size scale (paper, "Experiments").
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from pranet.core.actions import ActionTable
from pranet.core.se3 import Array, rotation_angle


def se3_distance(R_err: npt.ArrayLike, t_err: npt.ArrayLike) -> Array:
    """``D(T, 1) = ||t|| + angle(R)``. ``R_err: ([B,] 3, 3)``, ``t_err: ([B,] 3)`` -> ``([B])``."""
    return np.linalg.norm(np.asarray(t_err, dtype=np.float64), axis=-1) + rotation_angle(R_err)


def normalize_per_scale(rewards: npt.ArrayLike, table: ActionTable, eps: float = 1e-12) -> Array:
    """Scale each step-size group of ``rewards: ([B,] A)`` to unit L2 norm (zero groups stay zero)."""
    r = np.asarray(rewards, dtype=np.float64)
    # One (A, S) membership product for all groups: the walk calls this at every step, where a loop over the
    # scales with a norm each cost more than the rewards themselves.
    norms = np.sqrt((r * r) @ table.scale_members)  # ([B,] S)
    return r / np.maximum(norms, eps)[..., table.scale_index]


def true_rewards(R_err: npt.ArrayLike, t_err: npt.ArrayLike, table: ActionTable, normalize: bool = True) -> Array:
    """Exact rewards of every action. ``R_err: ([B,] 3, 3)``, ``t_err: ([B,] 3)`` -> ``([B,] A)``."""
    R_err = np.asarray(R_err, dtype=np.float64)
    t_err = np.asarray(t_err, dtype=np.float64)
    batched = R_err.ndim == 3
    if not batched:
        R_err, t_err = R_err[None], t_err[None]
    rot_before = rotation_angle(R_err)  # (B,)
    trans_before = np.linalg.norm(t_err, axis=-1)  # (B,)
    # Rotation actions: R_err @ R_a.T; translation actions: t_err - t_a (decoupled, paper Sec. "Reward function").
    # tr(R_err R_aᵀ) = Σ_ij R_err_ij R_a_ij: the angles after every action from one (B, 9) @ (9, A) product.
    trace_after = R_err.reshape(-1, 9) @ table.rotations.reshape(-1, 9).T  # (B, A)
    rot_after = np.arccos(np.clip((trace_after - 1.0) / 2.0, -1.0, 1.0))
    trans_after = np.linalg.norm(t_err[:, None, :] - table.translations[None], axis=-1)  # (B, A)
    rewards = np.where(table.is_rotation[None], rot_before[:, None] - rot_after, trans_before[:, None] - trans_after)
    if normalize:
        rewards = normalize_per_scale(rewards, table)
    return rewards if batched else rewards[0]


def point_rewards(
    clean_source: npt.ArrayLike,
    R_err: npt.ArrayLike,
    t_err: npt.ArrayLike,
    table: ActionTable,
    kind: str = "l2",
    clean_target: npt.ArrayLike | None = None,
    normalize: bool = True,
) -> Array:
    """Point-based rewards for the ablation (paper, "Reward function" under "Agent Design").

    ``clean_source: (N, 3)`` is the clean, complete source in its current pose, relative to the
    current centroid ``c``. ``kind="l2"``: mean distance of each point to its true position;
    ``kind="mcd"``: symmetric mean squared nearest-neighbour distance to ``clean_target`` (the true
    positions, relative to ``c``; computed from the state when not given). Returns ``(A,)``.
    """
    P = np.asarray(clean_source, dtype=np.float64)
    R_err = np.asarray(R_err, dtype=np.float64)
    t_err = np.asarray(t_err, dtype=np.float64)
    truth = P @ R_err.T + t_err if clean_target is None else np.asarray(clean_target, dtype=np.float64)

    if kind not in ("l2", "mcd"):
        raise ValueError(f"unknown point reward kind {kind!r}")
    if kind == "mcd":
        # KD-trees: brute-force N x N distances for each of the A actions cost ~1 s per state at N = 1024.
        from scipy.spatial import cKDTree  # training extra; the service never computes rewards

        truth_tree = cKDTree(truth)

    def distance(points: Array) -> float:
        if kind == "l2":
            return float(np.linalg.norm(points - (P @ R_err.T + t_err), axis=-1).mean())
        d_to_truth, _ = truth_tree.query(points)
        d_to_points, _ = cKDTree(points).query(truth)
        return float(np.mean(d_to_truth**2) + np.mean(d_to_points**2))

    before = distance(P)
    moved = np.einsum("aij,nj->ani", table.rotations, P) + table.translations[:, None, :]  # (A, N, 3)
    rewards = np.array([before - distance(m) for m in moved])
    return normalize_per_scale(rewards, table) if normalize else rewards
