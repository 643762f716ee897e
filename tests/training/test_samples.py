import numpy as np
import pytest

from pranet.core.actions import build_action_table
from pranet.core.reward import true_rewards
from pranet.core.se3 import rotation_angle
from pranet.training.samples import (
    SETTINGS,
    StateDistribution,
    curriculum_states,
    make_pair,
    observe,
    training_state,
)

TABLE = build_action_table()


@pytest.fixture
def shape():
    rng = np.random.default_rng(0)
    p = rng.standard_normal((1024, 3)) * [0.6, 0.4, 0.2]
    return p / np.linalg.norm(p, axis=1).max()


def test_settings_follow_the_protocol(shape):
    rng = np.random.default_rng(1)
    s, t = observe(shape, "clean", rng)
    assert len(s) == len(t) == 1024 and np.allclose(np.sort(s, axis=0), np.sort(t, axis=0))
    s, t = observe(shape, "noisy", rng)
    assert len(s) == len(t) == 512 and not np.allclose(s, t)
    assert np.abs(s - shape[np.argmin(np.linalg.norm(shape[None] - s[:, None], axis=-1), axis=1)]).max() <= 0.05 + 1e-9
    s, t = observe(shape, "partial", rng)
    assert len(s) == len(t) == round(0.7 * 512)
    with pytest.raises(ValueError):
        observe(shape, "foggy", rng)


@pytest.mark.parametrize("setting", SETTINGS)
def test_test_pair_ground_truth(shape, setting):
    pair = make_pair(shape, setting, np.random.default_rng(2))
    assert rotation_angle(pair.T_gt[:3, :3]) <= np.deg2rad(60) + 1e-9
    assert np.abs(pair.T_gt[:3, 3]).max() <= 0.5
    if setting == "clean":  # target = T_gt · source, shuffled
        moved = pair.source @ pair.T_gt[:3, :3].T + pair.T_gt[:3, 3]
        assert np.allclose(np.sort(moved, axis=0), np.sort(pair.target, axis=0))


def test_training_state_labels_match_the_geometry(shape):
    """Applying R_err about the source centroid and adding t_err aligns the source with the target."""
    states = StateDistribution(((60.0, 0.5, 1.0),), orientation_max_deg=60.0)
    rng = np.random.default_rng(3)
    for _ in range(5):
        st = training_state(shape, "clean", states, TABLE, rng)
        c = st.source.mean(0)
        aligned = (st.source - c) @ st.R_err.T + c + st.t_err
        nn = np.linalg.norm(st.target[None] - aligned[:, None], axis=-1).min(axis=1)
        assert nn.max() < 1e-9
        np.testing.assert_allclose(st.rewards, true_rewards(st.R_err, st.t_err, TABLE))
        assert rotation_angle(st.R_err) > 1e-3  # a real error, not the identity


def test_curriculum():
    full = ((60.0, 0.5, 1.0),)
    small = (10.0, 0.5 / 7)
    assert curriculum_states(0, 1300, "paper", full, small, 70 / 1300) == ((10.0, 0.5 / 7, 1.0),)
    assert curriculum_states(69, 1300, "paper", full, small, 70 / 1300) == ((10.0, 0.5 / 7, 1.0),)
    assert curriculum_states(70, 1300, "paper", full, small, 70 / 1300) == full
    assert curriculum_states(0, 32, "paper", full, small, 70 / 1300) == ((10.0, 0.5 / 7, 1.0),)
    assert curriculum_states(2, 32, "paper", full, small, 70 / 1300) == full  # scaled: round(32 * 70/1300) = 2
    assert curriculum_states(0, 10, "uniform", full, small, 0.1) == full
    assert len(curriculum_states(0, 10, "adhoc", full, small, 0.1)) == 2
