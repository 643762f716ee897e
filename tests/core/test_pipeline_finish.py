"""core.pipeline's last refinement of the winner: the polish on dense clouds, the robust finish of sparse partial
pairs, with a stand-in reward model (tests/oracle_scorer.py) and stand-in refinements."""

import numpy as np
import pytest
from oracle_scorer import (
    RangeLimitedOracle,
    asymmetric_cloud,
    rotated_problem,
    sparse_partial_pair,
    turned,
    unit_truth,
)

from pranet.core.metrics import isotropic_errors
from pranet.core.pipeline import register
from pranet.core.registration_config import RegistrationConfig
from pranet.core.registration_types import IcpResult


def test_the_polish_refines_the_winner_and_is_dropped_when_it_makes_it_worse():
    """On dense clouds ``polish`` runs once, on the winner; a polish that lands on the truth is kept, one that throws
    the result off (less confident, no longer converged) is dropped."""
    _, _, T = rotated_problem(40.0)
    src = asymmetric_cloud(np.random.default_rng(0), 20000)
    tgt = src @ T[:3, :3].T + T[:3, 3]
    truth = unit_truth(src, tgt, T)
    off = truth.copy()
    off[:3, 3] += 0.002  # an ICP that stops a little short: still converged, not exact
    short_icp = lambda s, t, init, res=None: IcpResult(off.copy(), 1.0, 0.0)  # noqa: E731
    polished = []

    def to_truth(s, t, T_unit, res):
        polished.append(T_unit)
        return truth.copy()

    config = RegistrationConfig(icp_stages=(("point_to_plane", 2.0),), exit_checks=(20, 40), polish=True)
    reg = register(
        src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), config, icp=short_icp, polish_fn=to_truth
    )
    assert len(polished) == 1 and np.allclose(polished[0], off)
    assert isotropic_errors(reg.T_target_source, T)[1] < 1e-6 and reg.timing_ms["polish"] > 0
    throw_off = lambda s, t, T_unit, res: np.eye(4)  # noqa: E731
    reg = register(
        src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), config, icp=short_icp, polish_fn=throw_off
    )
    np.testing.assert_allclose(reg.normalization.transform_to_unit(reg.T_target_source), off, atol=1e-9)
    reg = register(
        src,
        tgt,
        RangeLimitedOracle(src, tgt, T),
        np.random.default_rng(0),
        config.with_(polish=False),
        icp=short_icp,
        polish_fn=to_truth,
    )
    assert len(polished) == 1  # not asked for: not run


def test_the_polish_never_decides_the_status():
    """A ``suspect`` winner is not polished: on a wrong pose a finer refinement squeezes the overlap tighter and could
    lift it over the threshold, so the status is the ranking refinement's (a polish that lands on the truth does
    not make it ``converged`` either)."""
    src, tgt, T = rotated_problem(40.0)
    truth = unit_truth(src, tgt, T)
    off = truth.copy()
    off[:3, 3] += 0.01
    short_icp = lambda s, t, init, res=None: IcpResult(off.copy(), 1.0, 0.0)  # noqa: E731
    polished = []

    def to_truth(s, t, T_unit, res):
        polished.append(T_unit)
        return truth.copy()

    config = RegistrationConfig(icp_stages=(("point_to_plane", 2.0),), polish=True, threshold=1.01)  # never converged
    reg = register(
        src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), config, icp=short_icp, polish_fn=to_truth
    )
    assert polished == [] and reg.confidence.status == "suspect"
    np.testing.assert_allclose(reg.normalization.transform_to_unit(reg.T_target_source), off, atol=1e-9)


def test_sparse_partial_pairs_get_the_robust_finish_and_whole_ones_do_not():
    """A stand-in ICP that stops 2° short of the truth: on a sparse partial pair the finish (symmetric robust
    point-to-point) takes the winner nearer the truth; on the same shape with whole overlap it does not run, and
    the result is the ICP's."""
    from pranet.core.se3 import apply_transform

    config = RegistrationConfig(icp_stages=(("point_to_plane", 2.0),), exit_checks=(20, 40), polish=True)

    def run(src, tgt, T, polish=True):
        short = turned(2.0, [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]) @ unit_truth(src, tgt, T)
        icp = lambda s, t, init, res=None, proceed=None: IcpResult(short.copy(), 1.0, 0.0)  # noqa: E731
        oracle = RangeLimitedOracle(src, tgt, T)
        return register(src, tgt, oracle, np.random.default_rng(0), config.with_(polish=polish), icp=icp)

    src, tgt, T = sparse_partial_pair(0)
    reg = run(src, tgt, T)
    assert reg.confidence.overlap < 0.98
    assert isotropic_errors(reg.T_target_source, T)[0] < 1.0 and reg.timing_ms["polish"] > 0
    assert isotropic_errors(run(src, tgt, T, polish=False).T_target_source, T)[0] == pytest.approx(2.0, abs=1e-6)

    whole = asymmetric_cloud(np.random.default_rng(3))
    reg = run(whole, apply_transform(T, whole), T)
    assert reg.confidence.overlap >= 0.98
    assert isotropic_errors(reg.T_target_source, T)[0] == pytest.approx(2.0, abs=1e-6)
