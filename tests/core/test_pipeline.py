"""core.pipeline.register with a stand-in reward model (tests/oracle_scorer.py): confidence and global mode."""

import numpy as np
import pytest
from oracle_scorer import BatchedRangeLimitedOracle, RangeLimitedOracle
from scipy.spatial.transform import Rotation

from pranet.core.metrics import isotropic_errors
from pranet.core.pipeline import register
from pranet.core.se3 import make_transform
from pranet.core.starts import geodesic_distances, start_rotations


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


def test_identity_mode_carries_a_confidence():
    src, tgt, T = rotated_problem(20.0)
    reg = register(src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0))
    rot, trans = isotropic_errors(reg.transform, T)
    assert rot < 0.5 and trans < 0.01
    assert reg.confidence is not None and reg.confidence.score == pytest.approx(1.0)
    assert reg.confidence.status == "converged"
    assert reg.init == "identity" and reg.start_scores == []
    np.testing.assert_array_equal(reg.initial_transform, np.eye(4))
    assert {"preprocess", "target_embedding", "agent_steps", "icp", "confidence", "total"} <= set(reg.timing_ms)


def test_global_mode_finds_a_150_degree_rotation_that_identity_misses():
    """The stand-in knows only rotations within 60° of the answer, like the trained model: from the identity
    it fails (and says so), from the 24 starts one is within reach, and confidence picks it."""
    src, tgt, T = rotated_problem(150.0, scale=7.0)  # any units: the confidence lives in the unit frame
    assert np.degrees(geodesic_distances(T[None, :3, :3], start_rotations(24)).min()) < 60.0
    ident = register(src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0))
    assert isotropic_errors(ident.transform, T)[0] > 30.0
    assert ident.confidence.status == "suspect"

    oracle = BatchedRangeLimitedOracle(src, tgt, T)
    reg = register(src, tgt, oracle, np.random.default_rng(0), init="global")
    rot, trans = isotropic_errors(reg.transform, T)
    assert rot < 0.5 and trans < 0.01 * 7.0, (rot, trans)
    assert reg.confidence.status == "converged" and reg.confidence.score > 0.9
    assert oracle.batch_calls == [24] * 60  # one batched call per step for all starts
    assert len(reg.start_scores) == 24 and reg.start_scores[reg.start_index] == max(reg.start_scores)
    # The trajectory is the winning start's, from its start pose
    assert len(reg.trajectory) == 60
    np.testing.assert_allclose(reg.trajectory[-1][2], reg.agent_transform)
    start_R = reg.initial_transform[:3, :3]
    assert any(np.allclose(start_R, Q) for Q in start_rotations(24))


def test_global_mode_without_a_batched_scorer_and_with_fewer_starts():
    src, tgt, T = rotated_problem(150.0)
    oracle = RangeLimitedOracle(src, tgt, T)  # no batch_score_fn: score_fn is called per start
    reg = register(src, tgt, oracle, np.random.default_rng(0), init="global", n_starts=12, schedule=(20, 10))
    assert oracle.calls == 12 * 30
    assert len(reg.start_scores) == 12


def test_unknown_init_is_refused():
    src, tgt, T = rotated_problem(10.0)
    with pytest.raises(ValueError, match="init"):
        register(src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), init="random")
