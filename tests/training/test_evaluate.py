"""pranet-eval: the CLI end to end on a few real pairs, and the metric path with perfect estimates."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from pranet.core.actions import DEFAULT_SCHEDULE, build_action_table
from pranet.core.agent import oracle_score_fn
from pranet.core.preprocess import check_cloud, fit_normalization
from pranet.core.registration_config import SERVICE_DEFAULT
from pranet.engine.engine import Engine
from pranet.training import evaluate as ev
from pranet.training.samples import Pair, make_pair, pair_rng


@pytest.fixture
def shapes():
    """Three synthetic unit-sphere shapes (anisotropic blobs: no rotational symmetry), no data needed."""
    rng = np.random.default_rng(0)
    p = rng.standard_normal((3, 512, 3)) * [0.6, 0.4, 0.2]
    return p / np.linalg.norm(p, axis=2).max(axis=1)[:, None, None]


class OracleScorer:
    """A stand-in for the reward model that knows ``T_gt``: the exact rewards (``oracle_score_fn``).

    ``register`` normalises both clouds and resamples them; the oracle works in that unit frame and
    takes the first cloud it scores (the source before any action) as its reference.
    """

    def __init__(self, pair: Pair, n_points: int = 256):
        self.table = build_action_table()
        self.schedule = DEFAULT_SCHEDULE
        self.n_points = n_points
        norm = fit_normalization(check_cloud(pair.source, "source"), check_cloud(pair.target, "target"))
        self.T_unit = norm.transform_to_unit(pair.T_gt)

    def score_fn(self, target):
        state = {}

        def score(current, tgt):
            if "fn" not in state:
                state["fn"] = oracle_score_fn(self.T_unit, current, self.table)
            return state["fn"](current, tgt)

        return score


@pytest.mark.parametrize("setting", ["clean", "noisy"])
def test_perfect_estimate_has_zero_error(shapes, setting):
    perfect = ev.Runner(("perfect",), lambda pair, rng: {"perfect": ev.MethodOutput(pair.T_gt.copy(), 0.0)})
    out = ev.evaluate(shapes, setting, [perfect], seed=7, progress=False)
    s = out["summary"]["perfect"]
    assert s["n"] == 3 and s["success_rate"] == 1.0
    assert s["rotation_deg"] < 1e-5 and s["translation"] < 1e-9 and s["l2"] < 1e-9
    if setting == "clean":
        assert s["mcd"] < 1e-12
    else:  # the observed clouds are noisy subsets: only the noise remains (2 * 0.01² * 3 at most)
        assert 0 < s["mcd"] < 1e-3
    for rec in out["records"]["perfect"]:
        np.testing.assert_allclose(rec["T_est"], rec["T_gt"], atol=1e-9)


def test_wrong_estimate_is_measured(shapes):
    """A known error of 5° about z and 0.02 along x shows up as such (and is no success)."""
    c, s_ = np.cos(np.deg2rad(5.0)), np.sin(np.deg2rad(5.0))
    E = np.array([[c, -s_, 0, 0.02], [s_, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    off = ev.Runner(("off",), lambda pair, rng: {"off": ev.MethodOutput(pair.T_gt @ E, 0.0)})
    s = ev.evaluate(shapes, "clean", [off], progress=False)["summary"]["off"]
    assert s["rotation_deg"] == pytest.approx(5.0, abs=1e-6)
    assert s["translation"] == pytest.approx(0.02, abs=1e-9)
    assert s["success_rate"] == 0.0


def test_oracle_agent_through_the_pranet_runner(shapes):
    """The agent with exact rewards lands within the fine step sizes (v1); ICP then closes the gap (v2)."""
    pair = make_pair(shapes[0], "clean", pair_rng(1234, "clean", 0))
    runner = ev.pranet_runner(Engine(OracleScorer(pair)), ev.PRANET_METHODS)
    out = runner.fn(pair, np.random.default_rng(0))
    assert set(out) == {"pranet-v1", "pranet-v2", "pranet-adaptive"}
    assert len(out["pranet-v1"].trajectory) == sum(DEFAULT_SCHEDULE)
    # The adaptive run stops at its first exit check (ICP converges from there) and is as accurate.
    adaptive = out["pranet-adaptive"]
    first_check = SERVICE_DEFAULT.exit_checks[0]
    assert len(adaptive.trajectory) == adaptive.extra["checks"][0][0] == first_check < DEFAULT_SCHEDULE[0]
    va = ev.evaluate_pair(pair.source, pair.target, pair.clean_source, adaptive.transform, pair.T_gt)
    assert va.rotation_deg < 0.01 and va.translation < 1e-4 and not adaptive.extra["rescued"]
    assert out["pranet-v2"].ms >= out["pranet-v1"].ms  # v2 is timed as agent + ICP
    # v1 carries the confidence of the agent's own result (the flag measured on PRANet-v1 in RESULTS.md).
    assert 0.0 <= out["pranet-v1"].extra["confidence"] <= 1.0 and out["pranet-v1"].extra["status"] in (
        "converged",
        "suspect",
    )
    v1 = ev.evaluate_pair(pair.source, pair.target, pair.clean_source, out["pranet-v1"].transform, pair.T_gt)
    v2 = ev.evaluate_pair(pair.source, pair.target, pair.clean_source, out["pranet-v2"].transform, pair.T_gt)
    assert v1.rotation_deg < 1.0 and v1.translation < 0.02
    assert v2.rotation_deg < 0.01 and v2.translation < 1e-4 and v2.success
    cd, angle = ev.step_curves(pair, out["pranet-v1"].trajectory, sum(DEFAULT_SCHEDULE))
    assert len(cd) == len(angle) == 61 and angle[-1] < angle[0] and cd[-1] < cd[0]


def test_a_methods_randomness_does_not_depend_on_the_others_listed(shapes):
    """A stochastic method's draws (here its answer's translation) are the same alone, first or second in the list,
    and differ between methods and pairs."""

    def noisy(name):
        def fn(pair, rng):
            T = pair.T_gt.copy()
            T[:3, 3] += rng.normal(size=3)
            return {name: ev.MethodOutput(T, 0.0)}

        return ev.Runner((name,), fn)

    def draws(runners):
        out = ev.evaluate(shapes[:2], "clean", runners, progress=False)["records"]
        return {m: [np.asarray(r["T_est"])[:3, 3] for r in recs] for m, recs in out.items()}

    alone, first, second = draws([noisy("a")]), draws([noisy("a"), noisy("b")]), draws([noisy("b"), noisy("a")])
    for got in (first["a"], second["a"]):
        np.testing.assert_array_equal(np.array(got), np.array(alone["a"]))
    assert not np.allclose(first["a"], first["b"]) and not np.allclose(alone["a"][0], alone["a"][1])


def test_a_run_in_parts_draws_the_whole_runs_pairs(shapes):
    """``first_pair`` (``pranet-eval --skip``): pairs 2 and 3 evaluated on their own are pairs 2 and 3 of the whole run,
    with the same problems (hashes), indices and answers."""
    noisy = ev.Runner(
        ("a",),
        lambda pair, rng: {"a": ev.MethodOutput(pair.T_gt + np.pad(rng.normal(size=(3, 1)), ((0, 1), (3, 0))), 0.0)},
    )
    whole = ev.evaluate(shapes[:4], "noisy", [noisy], progress=False)["records"]["a"]
    part = ev.evaluate(shapes[2:4], "noisy", [noisy], progress=False, first_pair=2)["records"]["a"]
    for got, want in zip(part, whole[2:], strict=True):
        assert (got["pair"], got["pair_sha1"], got["T_est"]) == (want["pair"], want["pair_sha1"], want["T_est"])
    assert (
        part[0]["pair_sha1"]
        != ev.evaluate(shapes[2:3], "noisy", [noisy], progress=False)["records"]["a"][0]["pair_sha1"]
    )


def test_failing_method_counts_as_identity(shapes):
    def boom(pair, rng):
        raise ValueError("no luck")

    out = ev.evaluate(shapes[:1], "clean", [ev.Runner(("boom",), boom)], progress=False)
    rec = out["records"]["boom"][0]
    assert "no luck" in rec["error"] and rec["success"] is False
    assert out["summary"]["boom"]["n_errors"] == 1


def test_paper_reference_rows():
    assert ev.paper_reference("noisy", "pranet-v2")["rotation_deg"] == 2.900
    assert ev.paper_reference("clean", "pranet-v1", policy="stoch2")["rotation_deg"] == 3.669
    assert ev.paper_reference("clean", "pranet-v1", rotation="naive", trained_rotation="naive")["rotation_deg"] == 2.771
    assert ev.paper_reference("noisy", "ransac") is None
    assert ev.paper_reference("noisy", "icp", rotation="naive") is None


def test_cli_rejects_unknown_method():
    with pytest.raises(SystemExit):
        ev.parse_args(["--methods", "icp,teleport"])


@pytest.mark.data
def test_cli_noisy_all_methods(data_root, tmp_path):
    out = tmp_path / "eval.json"
    fig = tmp_path / "fig5.png"
    argv = ["--setting", "noisy", "--limit", "3", "--json", str(out), "--plot", str(fig)]
    assert ev.main([*argv, "--data-dir", str(data_root), "--quiet"]) == 0
    doc = json.loads(out.read_text())
    assert fig.stat().st_size > 0
    assert set(doc["summary"]) == set(ev.ALL_METHODS) == set(doc["records"])
    assert doc["config"]["n_pairs"] == 3 and doc["environment"]["cpu_count"]
    assert set(doc["paper"]) == {"icp", "fgr", "pranet-v1", "pranet-v2"}
    for method, s in doc["summary"].items():
        assert s["n"] == 3 and s["n_errors"] == 0, method
        for key in (*ev.METRICS, "success_rate", "ms_median"):
            assert s[key] is not None and math.isfinite(s[key]), (method, key)
    by_pair = {}
    for method, recs in doc["records"].items():
        assert [r["pair"] for r in recs] == [0, 1, 2]
        for r in recs:
            assert all(math.isfinite(r[k]) for k in ev.METRICS), (method, r)
            ref = by_pair.setdefault(r["pair"], (r["T_gt"], r["pair_sha1"], r["shape"]))
            assert (r["T_gt"], r["pair_sha1"], r["shape"]) == ref, method  # every method saw the same pair
    assert len({v[1] for v in by_pair.values()}) == 3
    curves = doc["fig5"]
    assert curves["n_pairs"] == 3 and len(curves["chamfer"]["mean"]) == 61
    # The shipped model has the fine phase's call, so the paper's agent runs it unless told not to: every fine step
    # is then a full network call (the trained call re-scores a translated source by the head alone).
    assert doc["config"]["fine_matching"] is True
    trained = tmp_path / "trained.json"
    argv = ["--setting", "noisy", "--limit", "3", "--methods", "pranet-v1", "--no-fine-matching"]
    assert ev.main([*argv, "--json", str(trained), "--data-dir", str(data_root), "--quiet"]) == 0
    doc_trained = json.loads(trained.read_text())
    assert doc_trained["config"]["fine_matching"] is False
    for fine, paper in zip(doc["records"]["pranet-v1"], doc_trained["records"]["pranet-v1"], strict=True):
        assert fine["network_calls"] >= 40 and fine["network_calls"] > paper["network_calls"], (fine, paper)
