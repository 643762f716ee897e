"""pranet-client: output of each option against a canned service, and one-line errors with a non-zero exit."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from client_helpers import canned_response, make_transform, run_console
from live_server import free_port
from numpy.testing import assert_allclose

from pranet.client.cli import main
from pranet.client.io import read_point_cloud, write_point_cloud

T_KNOWN = make_transform(20.0, (0.0, 0.0, 1.0), (0.5, 0.0, -0.25))


@pytest.fixture
def clouds(tmp_path: Path) -> tuple[Path, Path]:
    rng = np.random.default_rng(0)
    source = rng.normal(size=(300, 3))
    target = source @ T_KNOWN[:3, :3].T + T_KNOWN[:3, 3]
    return write_point_cloud(tmp_path / "a.ply", source), write_point_cloud(tmp_path / "b.xyz", target)


def run_cli(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return run_console("pranet-client", *args)


def assert_one_line_error(proc: subprocess.CompletedProcess[str], *fragments: str) -> None:
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: ")
    assert "Traceback" not in proc.stderr
    for fragment in fragments:
        assert fragment in lines[0]


# --- error paths, as a user meets them: the installed console script in a subprocess ---


def test_unreachable_server_is_one_line(clouds: tuple[Path, Path]) -> None:
    url = f"http://127.0.0.1:{free_port()}"
    proc = run_cli("register", *clouds, "--url", url)
    assert_one_line_error(proc, "cannot reach the service", url)
    assert proc.stdout == ""


def test_health_unreachable() -> None:
    assert_one_line_error(run_cli("health", "--url", f"http://127.0.0.1:{free_port()}"), "cannot reach")


def test_missing_file_is_one_line(tmp_path: Path, clouds: tuple[Path, Path]) -> None:
    missing = tmp_path / "nope.ply"
    proc = run_cli("register", missing, clouds[1], "--url", "http://127.0.0.1:1")
    assert_one_line_error(proc, str(missing), "no such")


def test_unreadable_file_is_one_line(tmp_path: Path, clouds: tuple[Path, Path]) -> None:
    bad = tmp_path / "bad.ply"
    bad.write_text("this is not a ply file\n")
    assert_one_line_error(run_cli("register", clouds[0], bad, "--url", "http://127.0.0.1:1"), "not a valid PLY")


def test_bad_output_path_fails_before_the_request(tmp_path: Path, clouds: tuple[Path, Path]) -> None:
    proc = run_cli("register", *clouds, "--url", "http://127.0.0.1:1", "--plot", tmp_path / "no" / "plot.png")
    assert_one_line_error(proc, "does not exist")
    proc = run_cli("register", *clouds, "--url", "http://127.0.0.1:1", "--save-aligned", tmp_path / "out.obj")
    assert_one_line_error(proc, "--save-aligned must end in one of")


def test_bad_arguments_exit_2(clouds: tuple[Path, Path]) -> None:
    assert run_cli("register", clouds[0]).returncode == 2
    assert run_cli("register", *clouds, "--steps", "a,b").returncode == 2


# --- output, in-process against a canned service on loopback ---


def test_summary(fake_service, clouds, capsys: pytest.CaptureFixture[str]) -> None:
    fake_service.routes[("POST", "/register")] = lambda body: (200, canned_response(T_KNOWN))
    assert main(["register", *map(str, clouds), "--url", fake_service.url]) == 0
    out = capsys.readouterr().out
    assert "T_target_source (target ≈ R @ source + t):" in out
    rows = [line.split() for line in out.splitlines() if line.startswith("  ")]
    assert_allclose(np.array(rows, dtype=float), T_KNOWN, atol=1e-6)
    assert "rotation: 20.000 deg" in out
    assert "ICP: fitness 0.9000, inlier_rmse 0.001" in out
    assert "timing (ms):" in out and "total 6.0" in out
    assert "model: fake 0" in out
    sent = fake_service.requests[-1]["json"]
    assert sent["icp"] is True and "steps" not in sent and "policy" not in sent
    assert_allclose(sent["source"], read_point_cloud(clouds[0]))


def test_options_are_sent(fake_service, clouds) -> None:
    fake_service.routes[("POST", "/register")] = lambda body: (200, canned_response(T_KNOWN))
    args = ["register", *map(str, clouds), "--url", fake_service.url, "--no-icp", "--steps", "5,10"]
    args += ["--policy", "stoch1", "--seed", "7", "--early-stop", "--api-key", "k3y"]
    assert main(args) == 0
    request = fake_service.requests[-1]
    assert request["headers"]["Authorization"] == "Bearer k3y"
    assert {k: request["json"][k] for k in ("icp", "steps", "policy", "seed", "early_stop")} == {
        "icp": False,
        "steps": [5, 10],
        "policy": "stoch1",
        "seed": 7,
        "early_stop": True,
    }


def test_exit_check_and_rescue_options(fake_service, clouds) -> None:
    fake_service.routes[("POST", "/register")] = lambda body: (200, canned_response(T_KNOWN))
    base = ["register", *map(str, clouds), "--url", fake_service.url]
    assert main(base) == 0
    assert not {"exit_checks", "rescue"} & set(fake_service.requests[-1]["json"])  # the server's defaults
    assert main([*base, "--exit-checks", "10,30", "--no-rescue"]) == 0
    sent = fake_service.requests[-1]["json"]
    assert sent["exit_checks"] == [10, 30] and sent["rescue"] is False
    assert main([*base, "--all-steps"]) == 0
    assert fake_service.requests[-1]["json"]["exit_checks"] == []
    assert "fine_matching" not in fake_service.requests[-1]["json"]
    assert main([*base, "--paper-steps", "--fine-matching"]) == 0
    sent = fake_service.requests[-1]["json"]
    assert sent["walk"] is False and sent["fine_matching"] is True
    assert main([*base, "--paper-steps", "--no-fine-matching"]) == 0
    assert fake_service.requests[-1]["json"]["fine_matching"] is False


def test_json_output_is_the_raw_response(fake_service, clouds, capsys) -> None:
    body = {**canned_response(T_KNOWN), "confidence": 0.5, "status": "converged"}
    fake_service.routes[("POST", "/register")] = lambda _: (200, body)
    assert main(["register", *map(str, clouds), "--url", fake_service.url, "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == body


def test_confidence_and_status_are_printed(fake_service, clouds, capsys) -> None:
    body = {**canned_response(T_KNOWN), "confidence": 0.5, "status": "converged"}
    fake_service.routes[("POST", "/register")] = lambda _: (200, body)
    assert main(["register", *map(str, clouds), "--url", fake_service.url]) == 0
    out = capsys.readouterr().out
    assert "status: converged, confidence: 0.500" in out and "certified" not in out
    certified = {**body, "confidence": 0.13, "matches": 255}  # ring LiDAR: converged on the global match's matches
    fake_service.routes[("POST", "/register")] = lambda _: (200, certified)
    assert main(["register", *map(str, clouds), "--url", fake_service.url]) == 0
    assert "status: converged, confidence: 0.130, certified by 255 feature matches" in capsys.readouterr().out


def test_save_aligned_and_plot(fake_service, clouds, tmp_path: Path) -> None:
    fake_service.routes[("POST", "/register")] = lambda _: (200, canned_response(T_KNOWN, steps=5))
    aligned, plot = tmp_path / "aligned.pcd", tmp_path / "plot.png"
    args = ["register", *map(str, clouds), "--url", fake_service.url, "--save-aligned", str(aligned)]
    assert main([*args, "--plot", str(plot)]) == 0
    assert_allclose(read_point_cloud(aligned), read_point_cloud(clouds[1]), atol=1e-5)
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and plot.stat().st_size > 10_000
    assert fake_service.requests[-1]["json"]["return_trajectory"] is True


def test_http_error_is_one_line(fake_service, clouds, capsys) -> None:
    fake_service.routes[("POST", "/register")] = lambda _: (401, {"detail": "missing or invalid API key"})
    assert main(["register", *map(str, clouds), "--url", fake_service.url]) == 1
    captured = capsys.readouterr()
    assert captured.err == "error: HTTP 401 from /register: missing or invalid API key\n"
    assert captured.out == ""


def test_health_ready_model(fake_service, capsys) -> None:
    fake_service.routes[("GET", "/health")] = lambda _: (200, {"status": "ok"})
    fake_service.routes[("GET", "/ready")] = lambda _: (503, {"detail": "model not loaded"})
    fake_service.routes[("GET", "/model")] = lambda _: (200, {"name": "fake"})
    assert main(["health", "--url", fake_service.url]) == 0
    assert json.loads(capsys.readouterr().out) == {"status": "ok"}
    assert main(["ready", "--url", fake_service.url]) == 1
    assert "model not loaded" in capsys.readouterr().err
    assert main(["model", "--url", fake_service.url]) == 0
    assert json.loads(capsys.readouterr().out) == {"name": "fake"}


def test_global_mode_options_and_a_plot_with_the_confidence(fake_service, clouds, tmp_path: Path) -> None:
    start = make_transform(90.0, (0.0, 0.0, 1.0), (0.0, 0.0, 0.0))
    body = {
        **canned_response(T_KNOWN, steps=4),
        "confidence": 0.8,
        "status": "converged",
        "initial_transform": start.tolist(),
    }
    fake_service.routes[("POST", "/register")] = lambda _: (200, body)
    plot = tmp_path / "plot.png"
    args = ["register", *map(str, clouds), "--url", fake_service.url, "--init", "global", "--starts", "6"]
    assert main([*args, "--plot", str(plot)]) == 0
    sent = fake_service.requests[-1]["json"]
    assert sent["init"] == "global" and sent["starts"] == 6
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_plot_draws_the_aligned_source_the_curves_and_the_confidence(clouds) -> None:
    """What ``--plot`` draws, read back from the figure: the "after" panel holds the source moved by the
    returned transform (computed here independently), the curves start at the angle between the global
    start and the result, and the title carries the confidence and status."""
    from matplotlib.colors import to_rgba

    from pranet.client.cli import registration_figure
    from pranet.client.client import RegistrationResult
    from pranet.client.io import read_point_cloud

    start = make_transform(90.0, (0.0, 0.0, 1.0), (0.0, 0.0, 0.0))
    body = {**canned_response(T_KNOWN, steps=4), "confidence": 0.8, "status": "converged"}
    result = RegistrationResult.from_json({**body, "initial_transform": start.tolist()})
    source, target = (read_point_cloud(p) for p in clouds)
    fig = registration_figure(source, target, result)
    title = fig.get_suptitle()
    assert "confidence 0.800 (converged)" in title and "ICP" in title
    after = fig.axes[1]
    assert after.get_title() == "after: T_target_source applied"
    (orange,) = [c for c in after.collections if np.allclose(c.get_facecolor()[0], to_rgba("tab:orange"))]
    xs, ys, zs = orange._offsets3d
    drawn = np.column_stack([xs, ys, zs])
    expected = source @ T_KNOWN[:3, :3].T + T_KNOWN[:3, 3]
    # Every drawn point is the moved copy of a source point (subsampled, so compare as sets).
    d = np.linalg.norm(drawn[:, None] - expected[None], axis=-1).min(axis=1)
    assert d.max() < 1e-6 and len(drawn) == min(len(source), 3000)
    rotation_curve = fig.axes[2].lines[0].get_ydata()
    assert len(rotation_curve) == len(result.trajectory) + 1
    R_gap = T_KNOWN[:3, :3].T @ start[:3, :3]
    assert rotation_curve[0] == pytest.approx(np.degrees(np.arccos(np.clip((np.trace(R_gap) - 1) / 2, -1, 1))))


def test_result_keeps_the_initial_transform() -> None:
    from pranet.client.client import RegistrationResult

    start = make_transform(90.0, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))
    result = RegistrationResult.from_json({**canned_response(T_KNOWN), "initial_transform": start.tolist()})
    assert_allclose(result.initial_transform, start)
    assert RegistrationResult.from_json(canned_response(T_KNOWN)).initial_transform is None


def test_url_and_api_key_come_from_the_environment(fake_service, clouds, monkeypatch, capsys) -> None:
    """README: `--url` (or `$PRANET_URL`), `--api-key` (or `$PRANET_API_KEY`)."""
    fake_service.routes[("GET", "/health")] = lambda _: (200, {"status": "ok"})
    fake_service.routes[("POST", "/register")] = lambda _: (200, canned_response(T_KNOWN))
    monkeypatch.setenv("PRANET_URL", fake_service.url)
    monkeypatch.setenv("PRANET_API_KEY", "from-env")
    assert main(["health"]) == 0
    assert main(["register", *map(str, clouds)]) == 0
    assert [r["path"] for r in fake_service.requests] == ["/health", "/register"]
    assert all(r["headers"].get("Authorization") == "Bearer from-env" for r in fake_service.requests)
    # A flag still wins over the environment.
    monkeypatch.setenv("PRANET_URL", "http://127.0.0.1:9")
    assert main(["health", "--url", fake_service.url]) == 0
    assert len(fake_service.requests) == 3
