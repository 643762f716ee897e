import time

import numpy as np
import pytest

from pranet.core.actions import build_action_table
from pranet.core.agent import (
    AgentTimeout,
    batch_from_single,
    choose_action,
    oracle_pose_fn,
    oracle_score_fn,
    run_agent,
    run_agent_batch,
)
from pranet.core.metrics import isotropic_errors
from pranet.core.sampling import sample_isotropic_rotations, sample_translations
from pranet.core.se3 import apply_transform, make_transform

TABLE = build_action_table()


def random_problem(rng, n=400):
    src = rng.standard_normal((n, 3)) * [0.5, 0.3, 0.2]
    T = make_transform(sample_isotropic_rotations(rng, np.deg2rad(60), 1)[0], sample_translations(rng, 0.5, 1)[0])
    return src, apply_transform(T, src)[rng.permutation(n)], T


def test_perfect_oracle_converges_within_60_steps():
    """The MDP itself: the greedy policy on the true rewards reaches < 0.5° and < 0.01 on clean pairs."""
    rng = np.random.default_rng(0)
    for _ in range(25):
        src, tgt, T = random_problem(rng)
        res = run_agent(src, tgt, oracle_score_fn(T, src, TABLE), TABLE)
        assert len(res.steps) == 60
        rot, trans = isotropic_errors(res.transform, T)
        assert rot < 0.5 and trans < 0.01, (rot, trans)


@pytest.mark.parametrize("walk_steps", [1, 5, 60])
def test_perfect_oracle_walk_converges_with_few_network_calls(walk_steps):
    """The walk: with the exact residual as the network's estimate, the greedy steps toward it reach the same
    accuracy as a call per step, and ask the estimator only when the walk arrives or its budget runs out: with an
    exact estimate, once per scale plus the arrival check (a long walk), or every step (``walk_steps=1``)."""
    rng = np.random.default_rng(0)
    for _ in range(10):
        src, tgt, T = random_problem(rng)
        pose = oracle_pose_fn(T, src)
        res = run_agent(src, tgt, oracle_score_fn(T, src, TABLE), TABLE, pose_fn=pose, walk_steps=walk_steps)
        rot, trans = isotropic_errors(res.transform, T)
        assert rot < 0.5 and trans < 0.01, (rot, trans)
        assert len(res.stopped_early) == 2  # each scale ended on arrival, not by running out of steps
        if walk_steps == 1:
            assert pose.calls[0] == len(res.steps) + 2  # every step, and the arrival of each scale
        else:
            assert pose.calls[0] <= 2 * (1 + len(res.steps) // walk_steps) + 2


def test_without_confirmation_an_arrival_ends_the_scale_with_no_further_call():
    """``confirm_arrival=False``: with an exact estimate, one call in all (the estimate serves both scales; the
    confirming run asks again at each arrival); the walk stops where the confirming run would have asked, so it
    takes the same steps."""
    rng = np.random.default_rng(6)
    src, tgt, T = random_problem(rng)
    confirming, quick = oracle_pose_fn(T, src), oracle_pose_fn(T, src)
    a = run_agent(src, tgt, None, TABLE, pose_fn=confirming, walk_steps=60)
    b = run_agent(src, tgt, None, TABLE, pose_fn=quick, walk_steps=60, confirm_arrival=False)
    assert quick.calls[0] == 1 and confirming.calls[0] == 3, (quick.calls, confirming.calls)
    assert [s.action for s in a.steps] == [s.action for s in b.steps]


def test_walk_takes_the_paper_loops_steps_until_it_arrives():
    """With an exact estimate the walk's rewards are the oracle's: the same actions, step for step, until the
    walk ends a scale on arrival (where the paper's loop oscillates about the goal)."""
    rng = np.random.default_rng(4)
    src, tgt, T = random_problem(rng)
    paper = run_agent(src, tgt, oracle_score_fn(T, src, TABLE), TABLE)
    walk = run_agent(src, tgt, None, TABLE, pose_fn=oracle_pose_fn(T, src), walk_steps=10)
    coarse = walk.stopped_early[0]
    assert [s.action for s in walk.steps[:coarse]] == [s.action for s in paper.steps[:coarse]]


def test_the_walk_never_scores_through_the_score_fn():
    rng = np.random.default_rng(5)
    src, tgt, T = random_problem(rng)

    def score(source, target):
        raise AssertionError("the walk must not call score_fn")

    run_agent(src, tgt, score, TABLE, pose_fn=oracle_pose_fn(T, src), walk_steps=3)


def test_trajectory_is_consistent():
    rng = np.random.default_rng(1)
    src, tgt, T = random_problem(rng)
    res = run_agent(src, tgt, oracle_score_fn(T, src, TABLE), TABLE)
    np.testing.assert_allclose(res.steps[-1].transform, res.transform)
    # Steps 0-19 use only coarse actions, 20-59 only fine ones.
    assert all(TABLE.actions[s.action].scale == 0 for s in res.steps[:20])
    assert all(TABLE.actions[s.action].scale == 1 for s in res.steps[20:])
    # A rotation step leaves the source centroid where it was (rotation about the current centroid).
    m = src.mean(axis=0)
    for prev, cur in zip(res.steps[:-1], res.steps[1:], strict=True):
        if TABLE.actions[cur.action].kind == "rotation":
            np.testing.assert_allclose(
                apply_transform(cur.transform, m[None]), apply_transform(prev.transform, m[None])
            )


def test_score_fn_sees_the_moved_source():
    seen = []

    def score(source, target):
        seen.append(source.mean(axis=0))
        r = np.zeros(len(TABLE))
        r[TABLE.names.index("trans+x:0.1")] = 1.0
        r[TABLE.names.index("trans+y:0.01")] = 1.0
        return r

    src = np.random.default_rng(2).standard_normal((50, 3))
    res = run_agent(src, src, score, TABLE, schedule=(3, 2))
    np.testing.assert_allclose(res.transform[:3, 3], [0.3, 0.02, 0.0], atol=1e-12)
    np.testing.assert_allclose(seen[-1] - seen[0], [0.3, 0.01, 0.0], atol=1e-12)


def test_early_stop_cuts_a_scale_when_no_reward_is_positive():
    calls = []

    def score(source, target):
        calls.append(1)
        return -np.ones(len(TABLE))

    src = np.random.default_rng(3).standard_normal((30, 3))
    res = run_agent(src, src, score, TABLE, early_stop=True)
    assert len(calls) == 2 and res.steps == [] and res.stopped_early == [0, 0]
    np.testing.assert_allclose(res.transform, np.eye(4))


def test_deadline_raises():
    src = np.random.default_rng(4).standard_normal((30, 3))
    with pytest.raises(AgentTimeout):
        run_agent(src, src, lambda s, t: np.ones(len(TABLE)), TABLE, deadline=time.monotonic() - 1)


def test_policies():
    r = np.array([0.1, 0.9, -0.5, 0.4, 0.0])
    assert choose_action(r, "deterministic", None) == 1
    rng = np.random.default_rng(0)
    picks = np.array([choose_action(r, "stoch1", rng) for _ in range(4000)])
    assert set(picks) <= {1, 3, 0}
    assert (picks == 1).mean() == pytest.approx(0.85 / 1.05, abs=0.03)
    picks = np.array([choose_action(r, "stoch2", rng) for _ in range(3000)])
    assert set(picks) == {0, 1, 3}  # uniform over positive rewards
    assert choose_action(-np.abs(r) - 1, "stoch2", rng) == int(np.argmax(-np.abs(r) - 1))
    with pytest.raises(ValueError):
        choose_action(r, "stoch1", None)
    with pytest.raises(ValueError):
        choose_action(r, "greedy", rng)


def test_stochastic_policies_are_seeded():
    rng_a, rng_b = np.random.default_rng(9), np.random.default_rng(9)
    src, tgt, T = random_problem(np.random.default_rng(5))
    fn = oracle_score_fn(T, src, TABLE)
    a = run_agent(src, tgt, fn, TABLE, policy="stoch1", rng=rng_a)
    b = run_agent(src, tgt, fn, TABLE, policy="stoch1", rng=rng_b)
    np.testing.assert_array_equal(a.transform, b.transform)


# --- The batched loop (global mode) -----------------------------------------------------------------


def _starts(rng, n):
    return np.stack(
        [
            make_transform(sample_isotropic_rotations(rng, np.pi, 1)[0], sample_translations(rng, 0.3, 1)[0])
            for _ in range(n)
        ]
    )


def test_batched_loop_equals_the_single_loop_per_start():
    """One batched oracle call per step takes, for every start, exactly the steps the single loop takes."""
    rng = np.random.default_rng(11)
    src, tgt, T = random_problem(rng, n=200)
    starts = _starts(rng, 5)
    single = oracle_score_fn(T, src, TABLE)
    calls = []

    def batched(sources, target):
        calls.append(len(sources))
        return batch_from_single(single)(sources, target)

    results = run_agent_batch(src, tgt, batched, TABLE, starts, schedule=(6, 4))
    assert calls == [5] * 10  # one call per step, all starts in it
    for T0, res in zip(starts, results, strict=True):
        ref = run_agent(src, tgt, single, TABLE, schedule=(6, 4), initial_transform=T0)
        assert [s.action for s in res.steps] == [s.action for s in ref.steps]
        np.testing.assert_array_equal(res.transform, ref.transform)
        for a, b in zip(res.steps, ref.steps, strict=True):
            np.testing.assert_array_equal(a.transform, b.transform)
            np.testing.assert_array_equal(a.rewards, b.rewards)


def test_batched_early_stop_shrinks_the_batch():
    """A start whose rewards are all negative leaves the batch for the rest of its scale."""
    src = np.random.default_rng(12).standard_normal((40, 3))
    starts = np.stack([np.eye(4), make_transform(np.eye(3), [5.0, 0.0, 0.0])])
    sizes = []

    def batched(sources, target):
        sizes.append(len(sources))
        r = np.ones((len(sources), len(TABLE)))
        r[sources.mean(axis=(1, 2)) > 1.0] = -1.0  # the second start (moved by +5 in x) stops at once
        return r

    results = run_agent_batch(src, src, batched, TABLE, starts, schedule=(3, 2), early_stop=True)
    assert sizes == [2, 1, 1, 2, 1]
    assert len(results[0].steps) == 5 and results[0].stopped_early == []
    assert results[1].steps == [] and results[1].stopped_early == [0, 0]
    np.testing.assert_allclose(results[1].transform, starts[1])


def test_batched_deadline_raises():
    src = np.random.default_rng(13).standard_normal((30, 3))
    with pytest.raises(AgentTimeout):
        run_agent_batch(
            src, src, lambda s, t: np.ones((len(s), len(TABLE))), TABLE, np.eye(4)[None], deadline=time.monotonic() - 1
        )


def test_each_step_is_the_named_action_about_the_current_centroid():
    """Every step, rebuilt independently with scipy: a rotation step turns the source by the action's angle
    about its *current* centroid (which stays put), a translation step adds the action's offset; the source
    sits far from the origin, so a rotation about the origin or a stale centroid would move the centroid."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    src, tgt, T = random_problem(rng)
    src = src + [5.0, -3.0, 2.0]
    tgt = apply_transform(T, src)
    res = run_agent(src, tgt, oracle_score_fn(T, src, TABLE), TABLE)
    prev = np.eye(4)
    for step in res.steps:
        kind, size = step.name.split(":")  # e.g. "rot-y", "0.5deg"
        number = float(size.removesuffix("deg"))
        sign = 1.0 if "+" in kind else -1.0
        axis = "xyz".index(kind[-1])
        moved = apply_transform(prev, src)
        c = moved.mean(axis=0)
        if kind.startswith("rot"):
            R = Rotation.from_rotvec(np.eye(3)[axis] * np.deg2rad(sign * number)).as_matrix()
            expected = (moved - c) @ R.T + c
        else:
            expected = moved + np.eye(3)[axis] * sign * number
        np.testing.assert_allclose(apply_transform(step.transform, src), expected, atol=1e-9)
        prev = step.transform


def test_the_fine_phase_is_scored_by_its_own_function():
    """``fine_score_fn`` scores every step after the first scale and ``score_fn`` none of them: a fine scorer that
    points the wrong way pulls the fine phase off, and the oracle's own fine phase ends where the oracle alone does."""
    rng = np.random.default_rng(7)
    src, tgt, T = random_problem(rng)
    oracle = oracle_score_fn(T, src, TABLE)
    seen: list[str] = []

    def coarse(s, t):
        seen.append("coarse")
        return oracle(s, t)

    def fine(s, t):
        seen.append("fine")
        return oracle(s, t)

    res = run_agent(src, tgt, coarse, TABLE, (20, 40), fine_score_fn=fine)
    assert seen == ["coarse"] * 20 + ["fine"] * 40
    alone = run_agent(src, tgt, oracle, TABLE, (20, 40))
    np.testing.assert_allclose(res.transform, alone.transform)
    wrong = run_agent(src, tgt, oracle, TABLE, (20, 40), fine_score_fn=lambda s, t: -oracle(s, t))
    assert isotropic_errors(wrong.transform, T)[0] > isotropic_errors(alone.transform, T)[0] + 5.0


def test_the_fine_phase_scorer_is_not_for_the_walk():
    rng = np.random.default_rng(8)
    src, tgt, T = random_problem(rng)
    oracle = oracle_score_fn(T, src, TABLE)
    with pytest.raises(ValueError, match="walk"):
        run_agent(src, tgt, oracle, TABLE, pose_fn=oracle_pose_fn(T, src), walk_steps=5, fine_score_fn=oracle)
