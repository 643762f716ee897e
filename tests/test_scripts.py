"""The scripts behind RESULTS.md run end to end on the shipped model (the smallest sizes), and what they print
agrees with their JSON: a refactor that breaks one shows here, not after an hour of reproduce_results.sh."""

from __future__ import annotations

import gzip
import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
pytest.importorskip("open3d")


def run_script(name: str, *args: str, data_root: Path) -> str:
    env = {"PRANET_DATA_DIR": str(data_root), "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"}
    out = subprocess.run(
        [sys.executable, str(REPO / "scripts" / name), *args], capture_output=True, text=True, timeout=600, env=env
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


@pytest.mark.slow
def test_global_eval_runs_and_reports_its_methods(data_root: Path, tmp_path: Path) -> None:
    path = tmp_path / "global.json"
    text = run_script(
        "global_eval.py", "--pairs", "1", "--methods", "pranet-global,ransac", "--json", str(path), data_root=data_root
    )
    rows = {row["method"]: row for row in json.loads(path.read_text())["summary"]}
    assert set(rows) == {"pranet-global", "ransac"}
    assert all(name in text for name in rows)


@pytest.mark.slow
def test_confidence_eval_scores_both_methods(data_root: Path, tmp_path: Path) -> None:
    path = tmp_path / "confidence.json"
    text = run_script(
        "confidence_eval.py",
        "--pairs",
        "3",
        "--calibration",
        "3",
        "--settings",
        "noisy",
        "--json",
        str(path),
        data_root=data_root,
    )
    assert "pranet-v1:" in text and "pranet-v2:" in text
    v1_line = text.split("pranet-v1:")[1].split("\n")[0]
    # Every v1 record carries its confidence (a missing one prints "median confidence success nan").
    assert "median confidence success 0." in v1_line or "median confidence success 1." in v1_line, v1_line


@pytest.mark.slow
def test_scan_check_prints_every_pair(scans_dir: Path) -> None:
    text = run_script("scan_check.py", data_root=scans_dir.parent)
    assert text.count("| service default |") == 3 and "v2 (60 steps + ICP)" in text


def test_results_tables_merges_and_writes_the_card_evaluation(tmp_path: Path) -> None:
    """Later files win a method's row; the card gets the PRANet rows' figures."""
    import shutil

    from pranet.engine.runtime import default_model_dir

    model = tmp_path / "model"
    shutil.copytree(default_model_dir(), model)
    files = [REPO / "results" / "baselines" / "eval-noisy.json.gz", REPO / "results" / "eval-noisy.json.gz"]
    out = subprocess.run(
        [
            sys.executable,
            str(REPO / "scripts" / "results_tables.py"),
            "--markdown",
            "--card",
            str(model),
            *map(str, files),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    newest = json.loads(gzip.decompress(files[1].read_bytes()))["summary"]["pranet-v1"]["rotation_deg"]
    card = json.loads((model / "card.json").read_text())
    assert card["evaluation"]["pranet-v1"]["noisy"]["rotation_deg"] == pytest.approx(newest)
    assert "| RANSAC+ICP |" in out.stdout  # the classical rows come from the first file
