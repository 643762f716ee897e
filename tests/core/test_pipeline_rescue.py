"""core.pipeline's rescues of a still unconfident result (restarts, shifted ICP starts, the wide ICP, the global
mode's starts, ICP from turned copies of the best), with a stand-in reward model (tests/oracle_scorer.py) and
stand-in ICPs."""

import numpy as np
import pytest
from oracle_scorer import (
    BatchedRangeLimitedOracle,
    RangeLimitedOracle,
    asymmetric_cloud,
    rotated_problem,
    snapping_icp,
    unit_truth,
)
from scipy.spatial.transform import Rotation

from pranet.core.metrics import isotropic_errors
from pranet.core.pipeline import register
from pranet.core.registration_config import RegistrationConfig
from pranet.core.registration_types import IcpResult


def test_rescue_icp_wins_only_when_it_is_more_confident():
    src, tgt, T = rotated_problem(150.0)  # out of the stand-in's reach: the agent fails, unconfidently
    truth = unit_truth(src, tgt, T)
    icp = snapping_icp(truth, 10.0)
    wide_ok = lambda s, t, init, res: snapping_icp(truth, 180.0)(s, t, init)  # noqa: E731
    reg = register(src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), icp=icp, rescue_icp=wide_ok)
    assert reg.rescued == "wide_icp" and isotropic_errors(reg.T_target_source, T)[0] < 1e-4
    assert reg.confidence.status == "converged"
    wide_bad = lambda s, t, init, res: snapping_icp(truth, 0.0)(s, t, init)  # noqa: E731  (stays at the input pose)
    reg = register(src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), icp=icp, rescue_icp=wide_bad)
    assert isotropic_errors(reg.T_target_source, T)[0] > 30.0
    assert reg.confidence.status == "suspect"


def test_restarts_around_the_estimate_rescue_a_rotation_beyond_reach():
    """The stand-in knows rotations within 35° only; the answer is 50° about x. With early stop the agent stays at
    the identity (all rewards negative), unconfident; the restart turned +30° about x is within reach, converges,
    and wins. Without restarts the result stays suspect."""
    src, tgt, T = rotated_problem(50.0, axis=(1.0, 0.0, 0.0))
    icp = snapping_icp(unit_truth(src, tgt, T), 5.0)
    args = (src, tgt)
    early = RegistrationConfig(early_stop=True)
    plain = register(*args, RangeLimitedOracle(src, tgt, T, reach_deg=35.0), np.random.default_rng(0), early, icp=icp)
    assert plain.confidence.status == "suspect" and plain.rescued is None
    oracle = BatchedRangeLimitedOracle(src, tgt, T, reach_deg=35.0)
    reg = register(*args, oracle, np.random.default_rng(0), early.with_(rescue_restarts=True), icp=icp)
    assert reg.rescued == "restarts" and reg.confidence.status == "converged"
    assert isotropic_errors(reg.T_target_source, T)[0] < 1e-4
    assert oracle.batch_calls and oracle.batch_calls[0] == 6  # six restarts, one batched call per step
    assert "rescue" in reg.timing_ms
    # The winning restart's trajectory is returned, from its start 30° about x off the identity.
    start_angle = np.degrees(np.linalg.norm(Rotation.from_matrix(reg.initial_transform[:3, :3]).as_rotvec()))
    assert start_angle == pytest.approx(30.0)
    np.testing.assert_allclose(reg.trajectory[-1][2], reg.agent_T_target_source)


@pytest.mark.parametrize("n_points", [20000, 300], ids=["dense", "sparse"])
def test_restarts_are_skipped_on_dense_clouds_after_the_global_match(n_points):
    """The same unconfident request with a global match that finds nothing: on a sparse cloud the restarts run (a
    batched call of six starts) and one of them wins; on a dense one they do not (the global match has searched
    every rotation there), and the wide ICP is what the rescue tries."""
    _, _, T = rotated_problem(50.0, axis=(1.0, 0.0, 0.0))
    src = asymmetric_cloud(np.random.default_rng(0), n_points)
    tgt = src @ T[:3, :3].T + T[:3, 3]
    icp = snapping_icp(unit_truth(src, tgt, T), 5.0)
    wide_calls = []

    def wide(s, t, init, res):
        wide_calls.append(1)
        return IcpResult(np.asarray(init).copy(), 0.0, 0.0)

    oracle = BatchedRangeLimitedOracle(src, tgt, T, reach_deg=35.0)
    config = RegistrationConfig(early_stop=True, rescue_restarts=True, global_match=True)
    reg = register(
        src,
        tgt,
        oracle,
        np.random.default_rng(0),
        config.with_(icp_stages=(("point_to_plane", 2.0),)),
        icp=icp,
        rescue_icp=wide,
        global_match_fn=lambda s, t, res, seed, viewpoint: iter(()),
    )
    if n_points < 1000:
        assert oracle.batch_calls[:1] == [6] and reg.rescued == "restarts" and wide_calls == []
    else:
        assert oracle.batch_calls == [] and reg.rescued is None and wide_calls == [1]


@pytest.mark.parametrize("n_points", [300, 20000], ids=["sparse", "dense"])
def test_global_starts_rescue_a_half_turn_on_sparse_clouds_only(n_points):
    """The answer is 150° about x: beyond the stand-in's 60° from the identity and from every restart 30° around it.
    On a sparse cloud the last rescue, the agent from the global mode's 24 starts (one batched call of 24 per step),
    reaches it and wins; on a dense one it does not run (the global match searches every rotation there), and the
    result stays suspect, as it does on the sparse cloud without that rescue or where the best scores above its
    gate."""
    _, _, T = rotated_problem(150.0, axis=(1.0, 0.0, 0.0))
    src = asymmetric_cloud(np.random.default_rng(0), n_points)
    tgt = src @ T[:3, :3].T + T[:3, 3]
    icp = snapping_icp(unit_truth(src, tgt, T), 5.0)
    config = RegistrationConfig(early_stop=True, rescue_restarts=True, rescue_global_starts=1.0)
    oracle = BatchedRangeLimitedOracle(src, tgt, T)
    reg = register(src, tgt, oracle, np.random.default_rng(0), config, icp=icp)
    sparse = n_points < 1000
    assert (24 in oracle.batch_calls) is sparse and oracle.batch_calls[:1] == [6]
    assert (reg.rescued == "global_starts") is sparse and (reg.confidence.status == "converged") is sparse
    assert (isotropic_errors(reg.T_target_source, T)[0] < 1e-4) is sparse
    if not sparse:
        return
    np.testing.assert_allclose(reg.trajectory[-1][2], reg.agent_T_target_source)  # the winning start's run
    for fraction in (None, 1e-3):  # off, or gated out: the best scores more than a thousandth of the threshold
        other = BatchedRangeLimitedOracle(src, tgt, T)
        plain = register(
            src, tgt, other, np.random.default_rng(0), config.with_(rescue_global_starts=fraction), icp=icp
        )
        assert 24 not in other.batch_calls and plain.confidence.status == "suspect"
        assert isotropic_errors(plain.T_target_source, T)[0] > 30.0


def test_the_global_starts_gate_is_a_fraction_of_the_threshold():
    with pytest.raises(ValueError, match="rescue_global_starts"):
        RegistrationConfig(rescue_global_starts=0.0)
    with pytest.raises(ValueError, match="rescue_global_starts"):
        RegistrationConfig(rescue_global_starts=1.5)


@pytest.mark.parametrize("n_points", [300, 20000], ids=["sparse", "dense"])
def test_turned_icp_rescues_a_half_turn_on_sparse_clouds_only(n_points):
    """The answer is 150° about x and the agent stays at the identity; the stand-in ICP lands on the truth from within
    40° only. On a sparse cloud the last rescue, ICP from the estimate turned by the global mode's well-spread
    rotations, reaches it, wins and stops there (the starts after the confident one are not refined); on a dense one,
    off, or gated out, it does not run and the result stays suspect."""
    from pranet.core.registration_config import TURNS
    from pranet.core.se3 import make_transform
    from pranet.core.starts import start_rotations

    _, _, T = rotated_problem(150.0, axis=(1.0, 0.0, 0.0))
    src = asymmetric_cloud(np.random.default_rng(0), n_points)
    tgt = src @ T[:3, :3].T + T[:3, 3]
    truth = unit_truth(src, tgt, T)
    turns = [isotropic_errors(make_transform(Q, np.zeros(3)), truth)[0] for Q in start_rotations(TURNS)]
    assert min(turns[1:]) < 40.0 < turns[0]  # a turned start within the stand-in's reach, the estimate not
    calls = []

    def icp(s, t, init, res=None, proceed=None):
        calls.append(isotropic_errors(init, truth)[0])
        return snapping_icp(truth, 40.0)(s, t, init)

    def run(config: RegistrationConfig):
        return register(src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), config, icp=icp)

    config = RegistrationConfig(early_stop=True, rescue_turns=1.0)
    reg = run(config)
    sparse = n_points < 1000
    assert (reg.rescued == "turned_icp") is sparse and (reg.confidence.status == "converged") is sparse
    assert (isotropic_errors(reg.T_target_source, T)[0] < 1e-4) is sparse
    if not sparse:
        assert len(calls) == 1  # the agent's own estimate only
        return
    assert calls[-1] < 40.0 and all(c >= 40.0 for c in calls[:-1])  # no start refined after the confident one
    for fraction in (None, 1e-3):  # off, or gated out: the best scores more than a thousandth of the threshold
        calls.clear()
        plain = run(config.with_(rescue_turns=fraction))
        assert len(calls) == 1 and plain.confidence.status == "suspect" and plain.rescued is None
        with pytest.raises(ValueError, match="rescue_turns"):
            RegistrationConfig(rescue_turns=0.0 if fraction is None else 1.5)


def test_shifted_starts_rescue_an_estimate_whose_translation_is_out_of_icp_reach():
    """The truth is a shift of 0.3 (unit frame) along x; the agent takes no step, and the stand-in ICP reaches the
    truth only from within 0.1 of its translation. On a sparse cloud the rescue's shifted starts (0.15 and 0.3 along
    each axis) find it; on a dense one they do not run; without them the result stays suspect."""
    from pranet.core.preprocess import fit_normalization
    from pranet.core.se3 import make_transform

    def problem(n_points: int):
        src = asymmetric_cloud(np.random.default_rng(0), n_points)
        scale = fit_normalization(src, src).scale
        T = make_transform(np.eye(3), [0.3 / scale, 0.0, 0.0])
        return src, src + T[:3, 3], T

    def translation_reach_icp(truth):
        def icp(source, target, init, resolution=None, proceed=None):
            close = np.linalg.norm(np.asarray(init)[:3, 3] - truth[:3, 3]) < 0.1
            return IcpResult((truth if close else np.asarray(init)).copy(), 1.0 if close else 0.0, 0.0)

        return icp

    still = RegistrationConfig(schedule=(0, 0), rescue_shifts=(0.15, 0.3))
    for n_points, shifted in ((300, True), (20000, False)):
        src, tgt, T = problem(n_points)
        icp = translation_reach_icp(unit_truth(src, tgt, T))
        reg = register(src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), still, icp=icp)
        assert (reg.candidate == "shifted_icp") is shifted and (reg.rescued == "shifted_icp") is shifted
        assert (isotropic_errors(reg.T_target_source, T)[1] < 1e-9) is shifted
        assert reg.confidence.status == ("converged" if shifted else "suspect")
    src, tgt, T = problem(300)
    icp = translation_reach_icp(unit_truth(src, tgt, T))
    plain = register(
        src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), still.with_(rescue_shifts=()), icp=icp
    )
    assert plain.confidence.status == "suspect" and plain.candidate == "agent"
