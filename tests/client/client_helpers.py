"""Helpers shared by the client tests (imported by name: pytest puts this folder and ``tests/`` on sys.path)."""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from live_server import LiveServer, clean_env, console_script, start_live_server

READY_TIMEOUT_S = 120.0


def make_transform(angle_deg: float, axis: tuple[float, float, float], translation: tuple[float, float, float]):
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    axis_arr = np.asarray(axis, dtype=np.float64)
    T[:3, :3] = Rotation.from_rotvec(np.radians(angle_deg) * axis_arr / np.linalg.norm(axis_arr)).as_matrix()
    T[:3, 3] = translation
    return T


def canned_response(T: np.ndarray, steps: int = 3) -> dict[str, Any]:
    """A ``POST /register`` body in the service's contract, with ``T`` as the answer."""
    return {
        "transform": T.tolist(),
        "rotation": T[:3, :3].tolist(),
        "translation": T[:3, 3].tolist(),
        "trajectory": [
            {"step": i + 1, "action": "rot+x:10deg", "transform": (np.eye(4) if i < steps - 1 else T).tolist()}
            for i in range(steps)
        ],
        "icp": {"applied": True, "fitness": 0.9, "inlier_rmse": 0.001},
        "timing_ms": {"preprocess": 1.0, "agent_steps": 2.0, "icp": 3.0, "total": 6.0},
        "model": {"name": "fake", "version": "0", "sha256": "ab" * 32},
    }


def run_console(name: str, *args: str | Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """Run console script ``name`` with ``args`` in a clean environment (plus ``env``); capture text output."""
    cmd = [console_script(name), *map(str, args)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=180, env=clean_env(env))


def start_server(log_dir: Path, api_key: str | None = None) -> LiveServer:
    """``pranet-serve`` with the shipped model and default limits (clouds of 40k points pass), waited for ``/ready``.

    Unlike the shared ``live_server`` fixture, whose small limits suit the limit tests, nothing is lowered.
    """
    from pranet.client import PranetClient, PranetError

    settings = {"PRANET_THREADS": "1", "PRANET_LOG_LEVEL": "warning"}
    if api_key:
        settings["PRANET_API_KEY"] = api_key
    server = start_live_server(log_dir, settings)
    with PranetClient(server.url, api_key=api_key, timeout=5.0) as client:
        try:
            client.wait_ready(timeout=READY_TIMEOUT_S)
        except PranetError as e:
            server.stop()
            pytest.fail(f"pranet-serve not ready: {e}\n{server.output()[-3000:]}")
    return server
