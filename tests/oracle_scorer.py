"""A stand-in for the reward model in pipeline tests: exact rewards within reach of the answer.

Imported by name (tests/ is on ``sys.path`` through its conftest). The trained model knows rotations up
to 60°; ``RangeLimitedOracle`` gives the true rewards (``core.reward.true_rewards``) while the current
rotation error is within ``reach_deg`` and all-negative rewards beyond (the agent then walks off with
the first action), so tests of the global mode do not depend on a model's accuracy.

It reads the current pose off the moved source by Kabsch: with ``n_points == len(source)`` the
pipeline's resampling is a permutation, and the rows are matched by their distance to the centroid
(unique for a random cloud, unchanged by rigid motion).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from pranet.core.actions import DEFAULT_SCHEDULE, ActionTable, build_action_table
from pranet.core.metrics import isotropic_errors
from pranet.core.preprocess import fit_normalization
from pranet.core.reward import true_rewards
from pranet.core.se3 import apply_transform, make_transform, rotation_angle


class RangeLimitedOracle:
    def __init__(
        self,
        source: np.ndarray,
        target: np.ndarray,
        T_target_source: np.ndarray,
        reach_deg: float = 60.0,
        table: ActionTable | None = None,
    ):
        self.table = table or build_action_table()
        self.schedule = DEFAULT_SCHEDULE
        self.n_points = len(source)
        norm = fit_normalization(np.asarray(source, float), np.asarray(target, float))
        src = norm.to_unit(source)  # (N, 3)
        T = norm.transform_to_unit(T_target_source)
        self.m = src.mean(axis=0)
        self.ref = src[np.argsort(np.linalg.norm(src - self.m, axis=1))] - self.m  # (N, 3) centred, sorted
        self.R_gt = T[:3, :3]
        self.goal = self.R_gt @ self.m + T[:3, 3]  # where the source centroid must go
        self.reach = np.deg2rad(reach_deg)
        self.calls = 0
        self.batch_calls: list[int] = []

    def rewards(self, current: np.ndarray) -> np.ndarray:
        """``current: (N, 3)``, the source in its current pose (unit frame) -> ``(A,)``."""
        self.calls += 1
        c = current.mean(axis=0)
        cur = current[np.argsort(np.linalg.norm(current - c, axis=1))] - c
        U, _, Vt = np.linalg.svd(self.ref.T @ cur)
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
        R_err = self.R_gt @ (Vt.T @ D @ U.T).T
        if rotation_angle(R_err) > self.reach:
            return -np.ones(len(self.table))
        return true_rewards(R_err, self.goal - c, self.table)

    def score_fn(self, target: np.ndarray):
        return lambda source, _target: self.rewards(source)


class BatchedRangeLimitedOracle(RangeLimitedOracle):
    """The same, with a ``batch_score_fn`` (records the batch size of every call)."""

    def batch_score_fn(self, target: np.ndarray):
        def score(sources: np.ndarray, _target: np.ndarray) -> np.ndarray:
            self.batch_calls.append(len(sources))
            return np.stack([self.rewards(s) for s in sources])

        return score


# Problems and an ICP stand-in for the pipeline and service tests.


def asymmetric_cloud(rng: np.random.Generator, n: int = 300) -> np.ndarray:
    """Points on an ellipsoid with a smaller one stuck to its side: no rotational symmetry."""
    u = rng.standard_normal((n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    big = n * 3 // 4
    return np.concatenate([u[:big] * [0.9, 0.5, 0.3], u[big:] * [0.2, 0.2, 0.3] + [0.4, 0.5, 0.1]])


def rotated_problem(angle_deg: float, axis=(1.0, 2.0, -1.0), scale: float = 1.0):
    src = asymmetric_cloud(np.random.default_rng(0)) * scale
    axis = np.asarray(axis) / np.linalg.norm(axis)
    T = make_transform(
        Rotation.from_rotvec(np.deg2rad(angle_deg) * axis).as_matrix(), np.array([0.3, -0.2, 0.1]) * scale
    )
    return src, src @ T[:3, :3].T + T[:3, 3], T


def snapping_icp(T_unit_truth: np.ndarray, reach_deg: float):
    """An ICP stand-in: lands exactly on the truth from within ``reach_deg``, else returns its start."""
    from pranet.core.registration_types import IcpResult

    def icp(source, target, init, resolution=None, proceed=None):  # proceed: no stages to cut short
        close = isotropic_errors(init, T_unit_truth)[0] < reach_deg
        return IcpResult((T_unit_truth if close else init).copy(), 1.0 if close else 0.0, 0.0)

    return icp


def unit_truth(src, tgt, T):
    from pranet.core.preprocess import fit_normalization

    return fit_normalization(src, tgt).transform_to_unit(T)


def turned(angle_deg: float, axis, t) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    return make_transform(Rotation.from_rotvec(np.deg2rad(angle_deg) * axis / np.linalg.norm(axis)).as_matrix(), t)


def sparse_partial_pair(seed: int):
    """A bumpy ellipsoid sampled twice (512 points each, noise sigma 0.01), each view keeping the 70 % of its points
    lowest along a random direction, the target turned 30° and shifted: ModelNet40's partial setting."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((4096, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = 1 + 0.15 * np.sin(3 * u[:, 0]) * np.cos(2 * u[:, 1]) + 0.1 * np.sin(4 * u[:, 2])
    shape = u * r[:, None] * [0.8, 0.55, 0.35]

    def view() -> np.ndarray:
        points = shape[rng.choice(4096, 512, replace=False)] + rng.normal(0, 0.01, (512, 3))
        return points[np.argsort(points @ rng.normal(size=3))[: int(0.7 * 512)]]

    source, target = view(), view()
    T = turned(30.0, rng.normal(size=3), rng.uniform(-0.1, 0.1, 3))
    return source, apply_transform(T, target), T
