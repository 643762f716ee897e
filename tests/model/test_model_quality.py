"""The shipped model is a trained agent: alone (PRANet-v1, no ICP), on fixed pairs of the ``pranet-eval``
protocol and on a real bunny pair, it beats plain ICP from the identity and stays within the model card's own
figures (``card.json: evaluation``, written by ``scripts/results_tables.py --card``), with margin. A model with
random weights and the same card fails the same check (the test shows it can fail)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("open3d")

from pranet.core.metrics import isotropic_errors  # noqa: E402
from pranet.core.pipeline import register  # noqa: E402
from pranet.core.preprocess import fit_normalization  # noqa: E402
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


def test_a_random_weight_model_fails_the_same_check(test_shapes, tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    from pranet.core.actions import build_action_table
    from pranet.model.config import NetConfig
    from pranet.model.export import export_model
    from pranet.model.network import RewardNet

    card = json.loads((default_model_dir() / "card.json").read_text())
    torch.manual_seed(0)
    net = RewardNet(NetConfig.from_dict(card["net"]), build_action_table(card["actions"]["scales"])).eval()
    export_model(net, tmp_path / "random", {k: v for k, v in card.items() if k != "files"})
    model = RewardModel.load(tmp_path / "random", threads=1)
    assert quality_failures(model, test_shapes) != []


def test_shipped_agent_alone_on_the_bunny(scans_dir: Path) -> None:
    """bun000 -> bun045 (34°, real range scans, metres): the agent alone lands closer than ICP from the identity
    (in the same unit frame and window as pranet-eval's ICP baseline), and within the card's bound."""
    from pranet.client.io import read_point_cloud
    from pranet.training import baselines

    pairs = (scans_dir / "pairs.csv").read_text().splitlines()
    row = next(line for line in pairs if line.startswith("bunny_bun000_to_bun045,"))
    T_gt = np.array([float(x) for x in row.split(",")[3].split()]).reshape(4, 4)
    source, target = read_point_cloud(scans_dir / "bun000.ply"), read_point_cloud(scans_dir / "bun045.ply")
    model = RewardModel.load(default_model_dir(), threads=1)
    reg = register(source, target, model, np.random.default_rng(0), PAPER_V1)
    agent_rot, _ = isotropic_errors(reg.agent_T_target_source, T_gt)
    norm = fit_normalization(source, target)
    rng = np.random.default_rng(0)
    sub_s = norm.to_unit(source[rng.choice(len(source), 2000, replace=False)])
    sub_t = norm.to_unit(target[rng.choice(len(target), 2000, replace=False)])
    icp_rot, _ = isotropic_errors(norm.transform_to_world(baselines.icp(sub_s, sub_t)), T_gt)
    assert agent_rot < icp_rot, (agent_rot, icp_rot)
    assert agent_rot <= card_bound(model.card), (agent_rot, card_bound(model.card))
