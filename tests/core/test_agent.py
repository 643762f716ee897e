import time

import numpy as np
import pytest

from pranet.core.actions import build_action_table
from pranet.core.agent import AgentTimeout, choose_action, oracle_score_fn, run_agent
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
