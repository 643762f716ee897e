import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pranet.core.actions import DEFAULT_SCALES, build_action_table
from pranet.core.reward import normalize_per_scale, point_rewards, se3_distance, true_rewards


def test_default_table_is_the_papers_24_actions():
    table = build_action_table()
    assert len(table) == 24
    assert table.scales == DEFAULT_SCALES
    for scale, (deg, dist) in enumerate(DEFAULT_SCALES):
        idx = table.indices_of_scale(scale)
        assert len(idx) == 12
        rot = [table.actions[i] for i in idx if table.actions[i].kind == "rotation"]
        trans = [table.actions[i] for i in idx if table.actions[i].kind == "translation"]
        assert sorted((a.axis, a.sign) for a in rot) == sorted((a, s) for a in range(3) for s in (1, -1))
        assert all(np.isclose(np.rad2deg(a.step), deg) for a in rot)
        assert all(np.isclose(a.step, dist) for a in trans)
    # Each rotation action is the scipy rotation about its axis; translations are axis vectors.
    for i, a in enumerate(table.actions):
        if a.kind == "rotation":
            ref = Rotation.from_euler("xyz"[a.axis], a.sign * a.step).as_matrix()
            np.testing.assert_allclose(table.rotations[i], ref, atol=1e-12)
            assert not table.translations[i].any()
        else:
            np.testing.assert_allclose(table.rotations[i], np.eye(3))
            assert table.translations[i][a.axis] == pytest.approx(a.sign * a.step)


def test_third_scale_from_data_and_fingerprint_changes():
    t2 = build_action_table()
    t3 = build_action_table([*DEFAULT_SCALES, (0.05, 0.001)])
    assert len(t3) == 36 and len(t3.indices_of_scale(2)) == 12
    assert t2.fingerprint != t3.fingerprint
    assert build_action_table().fingerprint == t2.fingerprint


def test_reward_definition_against_direct_computation():
    """r_a(T) = D(T, 1) - D(a ⊕ T, 1), recomputed action by action, unnormalised."""
    table = build_action_table()
    rng = np.random.default_rng(0)
    R = Rotation.random(random_state=5).as_matrix()
    t = rng.uniform(-0.5, 0.5, 3)
    r = true_rewards(R, t, table, normalize=False)
    for i, a in enumerate(table.actions):
        if a.kind == "rotation":
            after = se3_distance(R @ table.rotations[i].T, t)
        else:
            after = se3_distance(R, t - table.translations[i])
        assert r[i] == pytest.approx(se3_distance(R, t) - after, abs=1e-12)


def test_rewards_are_decoupled_and_signed():
    table = build_action_table()
    # Pure translation error along +x: +x translation actions improve; rotation rewards only see the
    # rotation term (the translation terms cancel): each rotation costs exactly its own angle.
    r = true_rewards(np.eye(3), np.array([0.3, 0.0, 0.0]), table, normalize=False)
    assert r[table.names.index("trans+x:0.1")] == pytest.approx(0.1)
    assert r[table.names.index("trans-x:0.1")] == pytest.approx(-0.1)
    steps = np.array([table.actions[i].step for i in table.rotation_indices])
    np.testing.assert_allclose(r[table.rotation_indices], -steps, atol=1e-12)
    # Pure rotation error of 30° about z: rot+z decreases the error by 10°.
    Rz = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    r = true_rewards(Rz, np.zeros(3), table, normalize=False)
    assert r[table.names.index("rot+z:10deg")] == pytest.approx(np.deg2rad(10))
    assert r[table.names.index("rot-z:10deg")] == pytest.approx(-np.deg2rad(10))
    steps = np.array([table.actions[i].step for i in table.translation_indices])
    np.testing.assert_allclose(r[table.translation_indices], -steps, atol=1e-12)


def test_normalisation_per_scale_and_batch_equals_single():
    table = build_action_table()
    rng = np.random.default_rng(1)
    Rs = Rotation.random(8, random_state=9).as_matrix()
    ts = rng.uniform(-0.5, 0.5, (8, 3))
    batch = true_rewards(Rs, ts, table)
    for s in range(2):
        np.testing.assert_allclose(np.linalg.norm(batch[:, table.indices_of_scale(s)], axis=1), 1.0)
    for i in range(8):
        np.testing.assert_allclose(batch[i], true_rewards(Rs[i], ts[i], table))
    np.testing.assert_allclose(normalize_per_scale(np.zeros(24), table), 0.0)


def test_point_rewards_agree_in_sign_with_se3_rewards_for_translations():
    table = build_action_table()
    rng = np.random.default_rng(2)
    P = rng.standard_normal((200, 3)) * 0.3
    t = np.array([0.2, -0.1, 0.05])
    r_l2 = point_rewards(P, np.eye(3), t, table, kind="l2")
    r_se3 = true_rewards(np.eye(3), t, table)
    tr = table.translation_indices
    assert (np.sign(r_l2[tr]) == np.sign(r_se3[tr])).mean() > 0.9
    r_mcd = point_rewards(P, np.eye(3), t, table, kind="mcd")
    assert np.argmax(r_mcd[table.indices_of_scale(0)]) == np.argmax(r_se3[table.indices_of_scale(0)])


def test_mcd_rewards_match_brute_force_nearest_neighbours():
    """The KD-tree MCD equals the symmetric mean squared nearest-neighbour distance computed densely."""
    table = build_action_table()
    rng = np.random.default_rng(5)
    P = rng.standard_normal((150, 3)) * 0.3
    R_err = Rotation.from_rotvec([0.2, -0.4, 0.1]).as_matrix()
    t_err = np.array([0.05, 0.1, -0.2])
    truth = P @ R_err.T + t_err

    def mcd(points):
        d2 = ((points[:, None, :] - truth[None]) ** 2).sum(-1)
        return d2.min(1).mean() + d2.min(0).mean()

    moved = np.einsum("aij,nj->ani", table.rotations, P) + table.translations[:, None, :]
    expected = np.array([mcd(P) - mcd(m) for m in moved])
    got = point_rewards(P, R_err, t_err, table, kind="mcd", normalize=False)
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12)


def test_normalised_rewards_at_a_known_state_computed_by_hand():
    """30° about z and t = (0.2, 0, 0): the raw rewards from scipy's rotation magnitudes and plain distances,
    then each scale's block divided by its own L2 norm (grouped here by the names' step sizes)."""
    table = build_action_table()
    R = Rotation.from_euler("z", 30, degrees=True)
    t = np.array([0.2, 0.0, 0.0])
    raw = []
    for name in table.names:
        kind, size = name.split(":")
        sign = 1.0 if "+" in kind else -1.0
        axis = np.eye(3)["xyz".index(kind[-1])]
        if kind.startswith("rot"):
            step = Rotation.from_rotvec(axis * np.deg2rad(sign * float(size.removesuffix("deg"))))
            raw.append(R.magnitude() - (R * step.inv()).magnitude())
        else:
            raw.append(np.linalg.norm(t) - np.linalg.norm(t - sign * float(size) * axis))
    raw = np.array(raw)
    coarse = np.array([n.endswith(("10deg", ":0.1")) for n in table.names])
    expected = np.where(coarse, raw / np.linalg.norm(raw[coarse]), raw / np.linalg.norm(raw[~coarse]))
    np.testing.assert_allclose(true_rewards(R.as_matrix(), t, table), expected, atol=1e-12)
    np.testing.assert_allclose(true_rewards(R.as_matrix(), t, table, normalize=False), raw, atol=1e-12)


def test_se3_distance_is_translation_norm_plus_angle_per_row():
    """Eq. 1's D(T, 1), batched: each row's |t| plus its rotation angle (scipy's magnitude)."""
    from pranet.core.reward import se3_distance

    R = Rotation.random(5, random_state=3)
    t = np.random.default_rng(4).normal(size=(5, 3))
    expected = np.linalg.norm(t, axis=1) + R.magnitude()
    np.testing.assert_allclose(se3_distance(R.as_matrix(), t), expected, atol=1e-12)
    assert se3_distance(np.eye(3), [0.3, 0.4, 0.0]) == pytest.approx(0.5)


def test_l2_point_rewards_match_brute_force():
    """kind="l2": the mean distance of the points to their true positions, before minus after each action."""
    table = build_action_table()
    rng = np.random.default_rng(6)
    P = rng.standard_normal((80, 3)) * 0.3
    R_err = Rotation.from_rotvec([0.3, -0.1, 0.2]).as_matrix()
    t_err = np.array([0.1, -0.05, 0.2])
    truth = P @ R_err.T + t_err

    def l2(points):
        return np.sqrt(((points - truth) ** 2).sum(axis=1)).mean()

    moved = [P @ table.rotations[a].T + table.translations[a] for a in range(len(table))]
    expected = np.array([l2(P) - l2(m) for m in moved])
    np.testing.assert_allclose(point_rewards(P, R_err, t_err, table, kind="l2", normalize=False), expected, atol=1e-12)
