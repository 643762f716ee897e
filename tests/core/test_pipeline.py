"""core.pipeline.register with a stand-in reward model (tests/oracle_scorer.py): confidence, global mode, exit checks,
the global match and the ICP gate (the rescues and the finish: test_pipeline_rescue.py, test_pipeline_finish.py)."""

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

from pranet.core.confidence import ConfidenceEstimator
from pranet.core.metrics import isotropic_errors
from pranet.core.pipeline import STAGES, register
from pranet.core.registration_config import MIN_AGENT_POINTS, PAPER_AGENT_POINTS, RegistrationConfig
from pranet.core.registration_context import RANK_QUERIES, agent_sample, prepare
from pranet.core.registration_types import GlobalAnswer, IcpResult
from pranet.core.starts import geodesic_distances, start_rotations


def test_identity_mode_carries_a_confidence():
    src, tgt, T = rotated_problem(20.0)
    reg = register(src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0))
    rot, trans = isotropic_errors(reg.T_target_source, T)
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
    assert isotropic_errors(ident.T_target_source, T)[0] > 30.0
    assert ident.confidence.status == "suspect"

    oracle = BatchedRangeLimitedOracle(src, tgt, T)
    reg = register(src, tgt, oracle, np.random.default_rng(0), RegistrationConfig(init="global"))
    rot, trans = isotropic_errors(reg.T_target_source, T)
    assert rot < 0.5 and trans < 0.01 * 7.0, (rot, trans)
    assert reg.confidence.status == "converged" and reg.confidence.score > 0.9
    # One batched call per step: for all 24 starts in the coarse phase, for the 3 most confident in the fine one.
    assert oracle.batch_calls == [24] * 20 + [3] * 40
    assert len(reg.start_scores) == 24 and reg.start_scores[reg.start_index] == max(reg.start_scores)
    # The trajectory is the winning start's, from its start pose
    assert len(reg.trajectory) == 60
    np.testing.assert_allclose(reg.trajectory[-1][2], reg.agent_T_target_source)
    start_R = reg.initial_transform[:3, :3]
    assert any(np.allclose(start_R, Q) for Q in start_rotations(24))


def test_global_mode_without_a_batched_scorer_and_with_fewer_starts():
    src, tgt, T = rotated_problem(150.0)
    oracle = RangeLimitedOracle(src, tgt, T)  # no batch_score_fn: score_fn is called per start
    config = RegistrationConfig(init="global", n_starts=12, schedule=(20, 10))
    reg = register(src, tgt, oracle, np.random.default_rng(0), config)
    assert oracle.calls == 12 * 20 + 3 * 10  # the coarse phase from each start, the fine one from the best 3
    assert len(reg.start_scores) == 12


def test_unknown_init_is_refused():
    src, tgt, T = rotated_problem(10.0)
    with pytest.raises(ValueError, match="init"):
        register(src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), RegistrationConfig(init="random"))


def test_split_schedule_cuts_at_cumulative_steps():
    from pranet.core.pipeline import split_schedule

    assert split_schedule((20, 40), (20, 40)) == [(20, 0), (0, 20), (0, 20)]
    assert split_schedule((20, 40), (10, 30)) == [(10, 0), (10, 10), (0, 30)]
    assert split_schedule((20, 40), ()) == [(20, 40)]
    assert split_schedule((20, 40), (0, 60, 99)) == [(20, 40)]  # nothing to cut
    for checks in [(5,), (20,), (7, 33, 59), (1, 2, 3)]:
        segments = split_schedule((20, 40), checks)
        assert tuple(np.sum(segments, axis=0)) == (20, 40)


def test_exit_checks_without_an_exit_take_the_same_steps_as_one_run():
    src, tgt, T = rotated_problem(40.0)
    plain = register(src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0))
    never = lambda s, t, init, res: snapping_icp(np.eye(4), 0.0)(s, t, init)  # noqa: E731  (returns its start)
    reg = register(
        src,
        tgt,
        RangeLimitedOracle(src, tgt, T),
        np.random.default_rng(0),
        RegistrationConfig(exit_checks=(20, 40), threshold=1.01),
        icp=never,
    )
    assert [s for s, _ in reg.checks] == [20, 40]
    assert [n for _, n, _ in reg.trajectory] == [n for _, n, _ in plain.trajectory]
    assert [s for s, _, _ in reg.trajectory] == list(range(60))
    np.testing.assert_allclose(reg.agent_T_target_source, plain.agent_T_target_source, atol=1e-9)


def test_exit_check_stops_the_agent_once_icp_is_confident():
    src, tgt, T = rotated_problem(40.0)
    oracle = RangeLimitedOracle(src, tgt, T)
    reg = register(
        src,
        tgt,
        oracle,
        np.random.default_rng(0),
        RegistrationConfig(exit_checks=(20, 40)),
        icp=snapping_icp(unit_truth(src, tgt, T), 10.0),
    )
    assert oracle.calls == 20 and len(reg.trajectory) == 20  # the coarse phase only
    assert reg.checks == [(20, pytest.approx(1.0))]
    rot, trans = isotropic_errors(reg.T_target_source, T)
    assert rot < 1e-4 and trans < 1e-6
    assert reg.confidence.status == "converged" and not reg.rescued


def test_timing_stages_are_non_negative_and_add_up_to_the_total():
    """The breakdown pranet-bench reports: with exit checks that do not exit (ICP after 20 and 40 steps, then the
    final ICP) every stage is >= 0 and the stages account for the total."""
    import time

    src, tgt, T = rotated_problem(40.0)

    def slow_icp(s, t, init, res):  # 5 ms per call: a negative stage would show it counted twice
        time.sleep(0.005)
        return snapping_icp(np.eye(4), 0.0)(s, t, init)

    reg = register(
        src,
        tgt,
        RangeLimitedOracle(src, tgt, T),
        np.random.default_rng(0),
        RegistrationConfig(exit_checks=(20, 40), threshold=1.01),
        icp=slow_icp,
    )
    t = reg.timing_ms
    stages = (*STAGES, "other")
    assert all(t[k] >= 0.0 for k in stages), t
    assert t["icp"] >= 3 * 5.0  # two checks and the final refinement
    assert sum(t[k] for k in stages) == pytest.approx(t["total"], rel=1e-9)


def test_the_icp_gate_asks_for_the_rest_of_the_refinement_only_for_promising_candidates():
    """With ``icp_gate``, every refinement is offered a ``proceed`` that says yes to an estimate near the truth and
    no to one far off (its quick confidence against the gate times the threshold); without it, none."""
    src, tgt, T = rotated_problem(40.0)
    truth = unit_truth(src, tgt, T)
    verdicts = []

    def icp(s, t, init, res=None, proceed=None):
        if proceed is not None:
            verdicts.append((proceed(truth), proceed(np.eye(4))))
        return IcpResult(truth.copy(), 1.0, 0.0)

    config = RegistrationConfig(icp_stages=(("point_to_plane", 2.0),), exit_checks=(20, 40))
    register(src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), config.with_(icp_gate=0.25), icp=icp)
    assert verdicts and all(v == (True, False) for v in verdicts)
    verdicts.clear()
    register(src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), config, icp=icp)
    assert verdicts == []


def test_the_icp_guard_keeps_the_estimate_when_icp_makes_it_worse():
    """An ICP that throws a right estimate far off: with ``icp_guard`` the estimate (more confident) is kept and the
    result says no ICP was applied; without it (the paper's v2) the ICP result is the answer."""
    src, tgt, T = rotated_problem(20.0)
    far = np.eye(4)
    far[:3, 3] = [3.0, 0.0, 0.0]
    throw_off = lambda s, t, init, res=None, proceed=None: IcpResult(far.copy(), 0.0, 0.0)  # noqa: E731
    config = RegistrationConfig(icp_stages=(("point_to_plane", 2.0),))
    guarded = register(
        src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), config.with_(icp_guard=True), icp=throw_off
    )
    rot, trans = isotropic_errors(guarded.T_target_source, T)
    assert rot < 0.5 and trans < 0.01 and guarded.icp is None
    plain = register(src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), config, icp=throw_off)
    assert isotropic_errors(plain.T_target_source, T)[1] > 1.0 and plain.icp is not None


def test_global_candidates_are_asked_for_cheapest_first_until_one_is_confident():
    """The global match's candidates are a lazy sequence: a wrong one is refined and scored, the next is asked for,
    and once one is ``converged`` no more are computed (the finer KISS-Matcher grid and RANSAC cost 2-10x the coarse
    grid)."""
    src, tgt, T = rotated_problem(150.0)  # beyond the stand-in's reach: the global match decides
    truth = unit_truth(src, tgt, T)
    wrong = truth @ np.diag([-1.0, -1.0, 1.0, 1.0])  # turned 180° about the source's z axis
    asked = []

    def candidates(s, t, res, seed, viewpoint):
        for name, T_unit in (("coarse", wrong), ("fine", truth), ("ransac", wrong)):
            asked.append(name)
            yield GlobalAnswer(T_unit.copy())

    config = RegistrationConfig(icp_stages=(("point_to_plane", 2.0),), exit_checks=(20, 40), global_match=True)
    icp = snapping_icp(truth, 5.0)  # refines only what is already within 5° of the truth
    reg = register(
        src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), config, icp=icp, global_match_fn=candidates
    )
    assert asked == ["coarse", "fine"]
    assert reg.candidate == "global_match" and reg.confidence.status == "converged"
    assert isotropic_errors(reg.T_target_source, T)[0] < 1e-4


def test_an_agent_exit_short_of_sure_gets_the_global_match_as_a_rival():
    """``exit_confidence``: an agent estimate that is ``converged`` but below the bar does not end the request
    before the global match; the global candidate is asked for and the more confident wins. At or above the bar,
    the request ends at the exit check and the global match is never asked."""
    src, tgt, T = rotated_problem(40.0)
    truth = unit_truth(src, tgt, T)
    off = truth.copy()
    off[:3, :3] = Rotation.from_rotvec([0.0, 0.0, np.deg2rad(4.0)]).as_matrix() @ truth[:3, :3]  # 0.87: converged

    def short_icp(s, t, init, res=None, proceed=None):  # the agent's estimate stops short; the truth stays
        return IcpResult((truth if np.allclose(init, truth) else off).copy(), 1.0, 0.0)

    asked = []

    def candidates(s, t, res, seed, viewpoint):
        asked.append(seed)
        yield GlobalAnswer(truth.copy())

    def run(bar):
        config = RegistrationConfig(
            icp_stages=(("point_to_plane", 2.0),),
            exit_checks=(20, 40),
            global_match=True,
            exit_confidence=bar,
        )
        oracle = RangeLimitedOracle(src, tgt, T)
        return register(src, tgt, oracle, np.random.default_rng(0), config, icp=short_icp, global_match_fn=candidates)

    plain = run(None)  # the status threshold is the bar: the agent's converged estimate ends the request
    agent_score = plain.confidence.score
    assert plain.candidate == "agent" and plain.confidence.status == "converged" and asked == []
    assert agent_score < 1.0
    assert run(agent_score).candidate == "agent" and asked == []  # sure: at the bar
    rival = run(min(1.0, agent_score + 0.01))
    assert asked == [0] and rival.candidate == "global_match" and rival.confidence.score > agent_score
    assert isotropic_errors(rival.T_target_source, T)[1] < 1e-6


def _problem(n: int):
    """``rotated_problem(40°)``'s pose on an ``n``-point cloud."""
    _, _, T = rotated_problem(40.0)
    src = asymmetric_cloud(np.random.default_rng(0), n)
    return src, src @ T[:3, :3].T + T[:3, 3], T


@pytest.mark.parametrize("n_points", [20000, 300], ids=["dense", "sparse"])
def test_a_doubtful_agent_estimate_waits_behind_the_global_match_on_dense_clouds(n_points):
    """With ``defer_doubtful``, on a dense cloud, an agent estimate whose quick confidence after the ICP gate's
    iterations is between the gate and the status threshold is not refined further before the global match: a
    confident global candidate ends the request and the rest of that ICP never runs; when no global candidate is
    confident, the estimate is refined from where the gate left it and wins. Without it, and on a sparse cloud
    (where that ICP is cheap), the agent's estimate is refined in full first and the global match is never asked."""
    src, tgt, T = _problem(n_points)
    truth = unit_truth(src, tgt, T)
    clouds = prepare(src, tgt, 256, np.random.default_rng(0))
    estimator = ConfidenceEstimator(clouds.src_index, clouds.tgt_index, clouds.resolution)
    doubtful = truth.copy()
    doubtful[0, 3] += 1.5 * clouds.resolution.spacing  # where the gate's iterations leave the agent's estimate
    gate = 0.25
    assert gate * estimator.threshold <= estimator.evaluate(doubtful, RANK_QUERIES).score < estimator.threshold
    wrong = truth @ np.diag([-1.0, -1.0, 1.0, 1.0])
    starts = []

    def icp(s, t, init, res=None, proceed=None):
        starts.append(("gated" if proceed is not None else "full", init.copy()))
        if proceed is not None:
            near = isotropic_errors(init, truth)[0] < 12.0
            part = truth if np.allclose(init, truth) else doubtful if near else init
            if not proceed(part):
                return IcpResult(part.copy(), 0.5, 0.0)
            init = part
        return IcpResult((truth if isotropic_errors(init, truth)[0] < 12.0 else init).copy(), 1.0, 0.0)

    def run(candidates, defer=True):
        starts.clear()
        config = RegistrationConfig(
            icp_stages=(("point_to_plane", 2.0),), exit_checks=(20, 40), global_match=True, icp_gate=gate
        )
        return register(
            src,
            tgt,
            RangeLimitedOracle(src, tgt, T),
            np.random.default_rng(0),
            config.with_(defer_doubtful=defer),
            icp=icp,
            global_match_fn=lambda s, t, res, seed, viewpoint: iter([GlobalAnswer(c.copy()) for c in candidates]),
        )

    def refined_from_doubtful():
        return any(kind == "full" and np.allclose(init, doubtful) for kind, init in starts)

    def refined_first(reg):
        assert reg.candidate == "agent" and not refined_from_doubtful()
        assert len(starts) == 1  # the agent's refinement went on past the gate; no global candidate was refined

    if n_points < 1000:
        refined_first(run([truth]))
        return
    settled = run([truth])
    assert settled.candidate == "global_match" and settled.confidence.status == "converged"
    assert not refined_from_doubtful() and settled.checks == []

    waited = run([wrong])
    assert waited.candidate == "agent" and waited.confidence.status == "converged"
    assert refined_from_doubtful() and waited.checks == [(20, pytest.approx(1.0))]
    assert isotropic_errors(waited.T_target_source, T)[0] < 1e-4

    refined_first(run([truth], defer=False))


def test_an_early_exit_check_ends_the_request_only_when_sure_and_the_global_match_waits_for_the_coarse_phase():
    """With checks after 10, 20 and 40 steps: a pair within the agent's reach ends at the first check, sure, with
    no global candidate asked for; a pair beyond it goes on to the end of the coarse phase (20 steps) before the
    global match is asked, as with checks after 20 and 40 alone."""
    config = RegistrationConfig(
        icp_stages=(("point_to_plane", 2.0),), exit_checks=(10, 20, 40), global_match=True, exit_confidence=0.55
    )
    for angle, steps_before_global in ((40.0, None), (150.0, 20)):
        src, tgt, T = rotated_problem(angle)
        oracle = RangeLimitedOracle(src, tgt, T)
        asked_after = []

        def candidates(s, t, res, seed, viewpoint, oracle=oracle, asked_after=asked_after):
            asked_after.append(oracle.calls)  # one scored step per call: the agent's steps so far
            yield from ()

        truth = unit_truth(src, tgt, T)
        reg = register(
            src,
            tgt,
            oracle,
            np.random.default_rng(0),
            config,
            icp=snapping_icp(truth, 12.0),
            global_match_fn=candidates,
        )
        if steps_before_global is None:
            assert asked_after == [] and [step for step, _ in reg.checks] == [10]
            assert reg.confidence.status == "converged" and len(reg.trajectory) == 10
        else:
            assert asked_after == [steps_before_global]
            assert [step for step, _ in reg.checks][:2] == [10, 20]


@pytest.mark.parametrize("n_points", [20000, 300], ids=["dense", "sparse"])
def test_a_global_answer_on_enough_matches_that_icp_kept_is_converged_whatever_its_score(n_points):
    """On ring LiDAR every answer is loose at the data's spacing, the right one too: a global answer resting on
    enough feature matches (``core.confidence.CERTIFYING_MATCHES``) that ICP kept within a voxel wins ``converged``
    over a tighter but ``suspect`` candidate, with its own score. One match fewer, or an ICP that takes it away
    (3 voxels), leaves it ``suspect``; so do sparse clouds, where the certificate was never measured."""
    from pranet.core.confidence import CERTIFYING_MATCHES

    src, tgt, T = _problem(n_points)
    truth = unit_truth(src, tgt, T)
    clouds = prepare(src, tgt, 256, np.random.default_rng(0))
    estimator = ConfidenceEstimator(clouds.src_index, clouds.tgt_index, clouds.resolution)
    loose = truth.copy()
    loose[0, 3] += 1.5 * clouds.resolution.spacing  # suspect by its score
    assert estimator.evaluate(loose).status == "suspect"
    turned = np.eye(4)
    turned[:3, :3] = Rotation.from_euler("z", 150.0, degrees=True).as_matrix()

    def run(matches, moved_voxels=0.0):
        def icp(s, t, init, res=None, proceed=None):
            out = init.copy()
            out[1, 3] += moved_voxels * clouds.resolution.voxel
            return IcpResult(out, 1.0, 0.0)

        config = RegistrationConfig(icp_stages=(("point_to_plane", 2.0),), exit_checks=(20, 40), global_match=True)
        return register(
            src,
            tgt,
            RangeLimitedOracle(src, tgt, T @ turned),  # the agent walks to a wrong pose
            np.random.default_rng(0),
            config,
            icp=icp,
            global_match_fn=lambda s, t, res, seed, viewpoint: iter([GlobalAnswer(loose.copy(), matches)]),
        )

    certified = run(CERTIFYING_MATCHES)
    if n_points < 1000:
        assert certified.confidence.status == "suspect" and certified.confidence.matches == 0
        return
    assert certified.candidate == "global_match" and certified.confidence.status == "converged"
    assert certified.confidence.matches == CERTIFYING_MATCHES
    assert certified.confidence.score < estimator.threshold
    for short in (run(CERTIFYING_MATCHES - 1), run(CERTIFYING_MATCHES, moved_voxels=3.0)):
        assert short.confidence.status == "suspect" and short.confidence.matches == 0


def test_an_estimate_offered_again_is_not_refined_again():
    """An agent that stopped early reaches its next exit check where it stood at the last one: ``offer`` gives back
    the candidate that estimate became (and records the new name), without a second ICP; another estimate is
    refined."""
    from pranet.core.registration_context import RegistrationContext
    from pranet.core.stage_timer import StageTimer

    src, tgt, T = rotated_problem(20.0)
    clouds = prepare(src, tgt, 256, np.random.default_rng(0))
    refined = []

    def icp(s, t, init, res=None, proceed=None):
        refined.append(init.copy())
        return IcpResult(unit_truth(src, tgt, T), 1.0, 0.0)

    ctx = RegistrationContext(
        clouds=clouds,
        config=RegistrationConfig(icp_stages=(("point_to_plane", 2.0),)),
        scorer=None,
        schedule=(20, 40),
        rng=np.random.default_rng(0),
        seed=0,
        timer=StageTimer(STAGES),
        estimator=ConfidenceEstimator(clouds.src_index, clouds.tgt_index, clouds.resolution),
        icp=icp,
    )
    estimate = np.eye(4)
    first = ctx.offer("agent", estimate.copy(), agent_index=0)
    again = ctx.offer("restarts", estimate.copy(), agent_index=1)
    assert again is first and len(refined) == 1
    assert ctx.tried == {"agent": first.confidence.score, "restarts": first.confidence.score}
    ctx.offer("agent", unit_truth(src, tgt, T))
    assert len(refined) == 2


def test_a_tiny_cloud_is_padded_to_the_networks_minimum_and_a_larger_one_sampled_without_repeats():
    rng = np.random.default_rng(0)
    tiny = rng.normal(size=(10, 3))
    padded = agent_sample(tiny, 128, rng)
    assert len(padded) == MIN_AGENT_POINTS and {tuple(p) for p in padded} == {tuple(p) for p in tiny}
    cloud = rng.normal(size=(500, 3))
    sampled = agent_sample(cloud, 128, rng)
    assert len(np.unique(sampled, axis=0)) == 128 and np.isin(sampled, cloud).all()
    whole = agent_sample(cloud, 1024, rng)
    assert len(whole) == 500 and sorted(map(tuple, whole)) == sorted(map(tuple, cloud))


def test_the_agent_sees_the_configs_number_of_points_or_the_models():
    """``agent_points`` samples both clouds to that many points for the agent (the service's 128), each point once, and
    a smaller cloud whole; ``None``: the model's ``n_points``. Out-of-range counts are refused."""
    src, tgt, T = rotated_problem(20.0)
    seen, targets = [], []

    class Recording(RangeLimitedOracle):
        def score_fn(self, target):
            seen.append(len(target))
            targets.append(np.asarray(target))
            return lambda source, _target: (seen.append(len(source)), -np.ones(len(self.table)))[1]

    scorer = Recording(src, tgt, T)
    register(src, tgt, scorer, np.random.default_rng(0), RegistrationConfig(agent_points=64))
    assert set(seen) == {64}
    seen.clear()
    register(src, tgt, scorer, np.random.default_rng(0))
    assert set(seen) == {scorer.n_points} == {300}
    seen.clear()
    targets.clear()
    register(src, tgt, scorer, np.random.default_rng(0), RegistrationConfig(agent_points=PAPER_AGENT_POINTS))
    assert set(seen) == {300} and len(np.unique(targets[0], axis=0)) == 300  # all 300, none repeated
    for bad in (0, 8, PAPER_AGENT_POINTS + 1, 10**6):
        with pytest.raises(ValueError, match="agent_points"):
            RegistrationConfig(agent_points=bad)


def test_fine_matching_scores_the_fine_phase_by_the_models_fine_call():
    """``fine_matching``: the 40 fine steps go to the score function's ``fine`` (the model's ``score_fine.onnx``),
    the 20 coarse ones to the trained call, with exit checks cutting the schedule as before; a model without a
    fine-phase call is refused with a message that says so, and the walk cannot take one."""
    src, tgt, T = rotated_problem(40.0)
    oracle = RangeLimitedOracle(src, tgt, T)
    fine_calls = []

    class WithFineCall:
        table, schedule, n_points = oracle.table, oracle.schedule, oracle.n_points

        def score_fn(self, target):
            fn = oracle.score_fn(target)

            def score(source, _target):
                return fn(source, _target)

            def fine(source, _target):
                fine_calls.append(1)
                return oracle.rewards(source)

            score.fine = fine
            return score

    config = RegistrationConfig(fine_matching=True)
    reg = register(src, tgt, WithFineCall(), np.random.default_rng(0), config)
    assert oracle.calls == 60 and len(fine_calls) == 40 and len(reg.trajectory) == 60
    # Unset, the fine call is taken where the model has one and the agent makes a call per step (the paper's
    # configurations); not with the walk, nor when turned off.
    for unset_or_off, used in ((RegistrationConfig(), True), (config.with_(fine_matching=False), False)):
        fine_calls.clear()
        register(src, tgt, WithFineCall(), np.random.default_rng(0), unset_or_off)
        assert len(fine_calls) == (40 if used else 0), unset_or_off.fine_matching
    assert not RegistrationConfig(walk_steps=10).uses_fine_call(True) and RegistrationConfig().uses_fine_call(True)
    assert not RegistrationConfig().uses_fine_call(False) and config.uses_fine_call(False)
    plain = register(src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), RegistrationConfig())
    np.testing.assert_allclose(reg.agent_T_target_source, plain.agent_T_target_source, atol=1e-9)
    with pytest.raises(ValueError, match="no fine-phase call"):
        register(src, tgt, RangeLimitedOracle(src, tgt, T), np.random.default_rng(0), config)
    with pytest.raises(ValueError, match="walk"):
        RegistrationConfig(fine_matching=True, walk_steps=10)


def test_the_global_mode_ends_at_its_coarse_exit_check_when_the_best_start_is_sure():
    """Global mode with ICP and an exit check in the coarse phase: the most confident start is refined and scored
    after the coarse phase; sure, it ends the request (no fine phase from the best three, no global match). Without
    that check the fine phase runs from the best three, and a sure result there still spares the global match. An
    ICP that reaches only 1° cannot finish the coarse-phase estimate (6° off here, scored 0.93): under a bar of
    0.95 it is not sure at the check, the fine phase runs, and its result is sure in the end."""
    src, tgt, T = rotated_problem(150.0)
    truth = unit_truth(src, tgt, T)
    base = RegistrationConfig(init="global", icp_stages=(("point_to_plane", 2.0),), global_match=True)
    for exit_checks, reach, bar, ends_early in (
        ((10, 20, 40), 12.0, 0.55, True),
        ((40,), 12.0, 0.55, False),
        ((10, 20, 40), 1.0, 0.95, False),
    ):
        oracle = BatchedRangeLimitedOracle(src, tgt, T)
        asked = []

        def candidates(s, t, res, seed, viewpoint, asked=asked):
            asked.append(True)
            yield from ()

        reg = register(
            src,
            tgt,
            oracle,
            np.random.default_rng(0),
            base.with_(exit_checks=exit_checks, exit_confidence=bar),
            icp=snapping_icp(truth, reach),
            global_match_fn=candidates,
        )
        assert isotropic_errors(reg.T_target_source, T)[0] < 1e-4 and reg.confidence.status == "converged"
        if ends_early:
            assert oracle.batch_calls == [24] * 20 and asked == []
            assert [step for step, _ in reg.checks] == [20] and len(reg.trajectory) == 20
        else:
            assert oracle.batch_calls == [24] * 20 + [3] * 40
        assert asked == []


def test_an_unconfident_global_mode_result_gets_the_rescues_but_not_its_own_starts_again():
    """No start is within the stand-in's reach (5°), so the global mode's best is suspect: the rescues run as they
    do from the input pose (here the wide ICP, which reaches the truth), except the agent from the global starts,
    which the global mode has just run (no second coarse phase of 24)."""
    src, tgt, T = rotated_problem(150.0)
    truth = unit_truth(src, tgt, T)
    config = RegistrationConfig(init="global", rescue_global_starts=1.0)
    wide = lambda s, t, init, res: snapping_icp(truth, 180.0)(s, t, init)  # noqa: E731
    oracle = BatchedRangeLimitedOracle(src, tgt, T, reach_deg=5.0)
    reg = register(src, tgt, oracle, np.random.default_rng(0), config, icp=snapping_icp(truth, 10.0), rescue_icp=wide)
    assert reg.rescued == "wide_icp" and reg.confidence.status == "converged"
    assert isotropic_errors(reg.T_target_source, T)[0] < 1e-4
    assert oracle.batch_calls == [24] * 20 + [3] * 40
