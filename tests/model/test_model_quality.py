"""The shipped model is a trained agent: alone (PRANet-v1, no ICP), on fixed pairs of the ``pranet-eval``
protocol it beats plain ICP from the identity and stays within the model card's own figures (``card.json:
evaluation``, written by ``scripts/results_tables.py --card``), with margin; on a real bunny pair it removes most
of the misalignment. A model with random weights and the same card fails the same checks (they can fail)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("open3d")

from pranet.core.metrics import isotropic_errors  # noqa: E402
from pranet.core.pipeline import register  # noqa: E402
from pranet.core.registration_config import PAPER_V1  # noqa: E402
from pranet.engine.runtime import RewardModel, default_model_dir  # noqa: E402

PAIRS = 12  # the first pairs of pranet-eval's clean setting (seed 1234, unseen categories)
MARGIN_DEG = 2.0


def card_bound(card: dict) -> float:
    """The v1 median rotation error (clean) this check allows: twice the card's, plus a margin."""
    v1 = card["evaluation"]["pranet-v1"]["clean"]
    return 2.0 * v1["rotation_deg_median"] + MARGIN_DEG


def agent_vs_icp(model: RewardModel, shapes: np.ndarray) -> tuple[dict, dict]:
    from pranet.engine.engine import Engine
    from pranet.training import baselines
    from pranet.training.evaluate import baseline_runner, evaluate, pranet_runner

    runners = [pranet_runner(Engine(model), ("pranet-v1",)), baseline_runner("icp", baselines.icp)]
    summary = evaluate(shapes, "clean", runners, progress=False)["summary"]
    return summary["pranet-v1"], summary["icp"]


def quality_failures(model: RewardModel, shapes: np.ndarray) -> list[str]:
    v1, icp = agent_vs_icp(model, shapes)
    failures = []
    if not v1["rotation_deg"] < icp["rotation_deg"]:
        failures.append(f"agent mean {v1['rotation_deg']:.2f}° not below ICP's {icp['rotation_deg']:.2f}°")
    if not v1["rotation_deg_median"] <= card_bound(model.card):
        failures.append(
            f"agent median {v1['rotation_deg_median']:.2f}° above the card's bound {card_bound(model.card):.2f}°"
        )
    return failures


@pytest.fixture(scope="module")
def test_shapes(data_root: Path) -> np.ndarray:
    from pranet.training.data import load_modelnet40, test_indices

    data = load_modelnet40(data_root, "test")
    return data.points[test_indices(data.labels)][:PAIRS]


def test_shipped_agent_beats_icp_from_the_identity(test_shapes) -> None:
    model = RewardModel.load(default_model_dir(), threads=1)
    assert "evaluation" in model.card, "card.json has no evaluation: run scripts/results_tables.py --card"
    assert quality_failures(model, test_shapes) == []


@pytest.fixture(scope="module")
def random_model(tmp_path_factory) -> RewardModel:
    """A model with the shipped card and architecture but random weights (what the checks must reject)."""
    torch = pytest.importorskip("torch")
    from pranet.core.actions import build_action_table
    from pranet.model.config import NetConfig
    from pranet.model.export import export_model
    from pranet.model.network import RewardNet

    card = json.loads((default_model_dir() / "card.json").read_text())
    torch.manual_seed(0)
    net = RewardNet(NetConfig.from_dict(card["net"]), build_action_table(card["actions"]["scales"])).eval()
    out = tmp_path_factory.mktemp("random")
    export_model(net, out, {k: v for k, v in card.items() if k != "files"})
    return RewardModel.load(out, threads=1)


def test_a_random_weight_model_fails_the_same_check(test_shapes, random_model) -> None:
    assert quality_failures(random_model, test_shapes) != []


# The real scan: bun045 -> bun000 (34°, range scans in metres, 89 % overlap), the pair of the README's example.
# There the agent alone does not beat ICP from the identity (2.0.0: 6-10° over seeds against 2.6°; 1.1.0: 9°;
# RESULTS.md, "Real scans"), so this checks what it does reach: two thirds of the misalignment removed. It does not
# tell a trained 2.0.0 from a random one: on a dense, mostly overlapping pair the matching's position term is a
# soft ICP whatever the weights (a random-weight 2.0.0 reaches 6.1°). The ModelNet40 check above is the one a
# random model fails (12 clean pairs: mean 17.0° against the trained 5.2°).
BUNNY_SHARE = 1.0 / 3.0


def bunny_agent_error(model: RewardModel, scans_dir: Path) -> tuple[float, float]:
    """(the agent alone's rotation error, the initial rotation) on bun045 -> bun000, in degrees."""
    from pranet.client.io import read_point_cloud

    pairs = (scans_dir / "pairs.csv").read_text().splitlines()
    row = next(line for line in pairs if line.startswith("bunny_bun000_to_bun045,"))
    T_gt = np.linalg.inv(np.array([float(x) for x in row.split(",")[3].split()]).reshape(4, 4))
    source, target = read_point_cloud(scans_dir / "bun045.ply"), read_point_cloud(scans_dir / "bun000.ply")
    reg = register(source, target, model, np.random.default_rng(0), PAPER_V1)
    return isotropic_errors(reg.agent_T_target_source, T_gt)[0], isotropic_errors(np.eye(4), T_gt)[0]


def test_shipped_agent_alone_does_real_work_on_the_bunny(scans_dir: Path) -> None:
    agent_rot, initial = bunny_agent_error(RewardModel.load(default_model_dir(), threads=1), scans_dir)
    assert agent_rot < BUNNY_SHARE * initial, (agent_rot, initial)


def fine_phase_drift(model: RewardModel, shapes: np.ndarray, fine_matching: bool) -> np.ndarray:
    """The rotation errors (degrees) where the 40 fine steps end, started at the truth, on partial pairs."""
    from pranet.training.samples import make_pair, pair_rng

    config = PAPER_V1.with_(schedule=(0, 40), fine_matching=fine_matching)
    errors = []
    for i, shape in enumerate(shapes):
        pair = make_pair(shape, "partial", pair_rng(1234, "partial", i), 60.0, 0.5, "isotropic")
        at_truth = pair.source @ pair.T_gt[:3, :3].T + pair.T_gt[:3, 3]  # the truth is the identity now
        reg = register(at_truth, pair.target, model, np.random.default_rng(0), config)
        errors.append(isotropic_errors(reg.agent_T_target_source, np.eye(4))[0])
    return np.array(errors)


@pytest.fixture(scope="module")
def drift_shapes(data_root: Path) -> np.ndarray:
    from pranet.training.data import load_modelnet40, test_indices

    data = load_modelnet40(data_root, "test")
    return data.points[test_indices(data.labels)][:24]


def test_the_fine_call_keeps_a_partial_pair_where_it_belongs(drift_shapes) -> None:
    """What ``score_fine.onnx`` is for: from the true pose of a partial pair, the trained call's fine phase walks
    the source off (its feature-led first round and its matching about the crop's own centroid), the fine call's
    stays near (docs/DESIGN.md, "A fine-phase call")."""
    model = RewardModel.load(default_model_dir(), threads=1)
    # 2.2.0 on these 24 pairs: the trained call ends 9.0° / 9.2° off (mean / median), the fine call 4.4° / 3.3°.
    trained = fine_phase_drift(model, drift_shapes, fine_matching=False)
    fine = fine_phase_drift(model, drift_shapes, fine_matching=True)
    assert np.median(fine) < 0.5 * np.median(trained), (fine, trained)
    assert fine.mean() < 0.7 * trained.mean(), (fine, trained)


def test_the_twin_term_tells_a_symmetric_shape_from_its_turned_copies(data_root: Path) -> None:
    """What the twin term is for (``core.twins``): two clean test pairs that model 2.2.1, without it, ended 20° and
    73° off (a vase and a near-round shape turned about their own axes; docs/DESIGN.md, "The clean failures are turns
    about the shape's own axis"). The shipped model with the term finishes both; fed zeros for it, the same graphs
    end on the turned copies again."""
    from pranet.engine.engine import Engine
    from pranet.training.data import load_modelnet40, test_indices
    from pranet.training.samples import make_pair, pair_rng

    data = load_modelnet40(data_root, "test")
    shapes = data.points[test_indices(data.labels)]
    model = RewardModel.load(default_model_dir(), threads=1)
    assert model.twins is not None, "the shipped model's graphs do not take the twin term"
    blind = Engine(RewardModel.load(default_model_dir(), threads=1, use_twins=False))
    for i in (8, 21):
        pair = make_pair(shapes[i], "clean", pair_rng(1234, "clean", i), 60.0, 0.5)
        with_twins = Engine(model).register(pair.source, pair.target, PAPER_V1, np.random.default_rng(0))
        without = blind.register(pair.source, pair.target, PAPER_V1, np.random.default_rng(0))
        assert isotropic_errors(with_twins.T_target_source, pair.T_gt)[0] < 1.0
        assert isotropic_errors(without.T_target_source, pair.T_gt)[0] > 10.0
