"""Helpers shared by the client tests (imported by name: pytest puts this folder on sys.path)."""

from __future__ import annotations

import os
import shutil
import socket
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


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


def console_script(name: str) -> str:
    """The console script ``name`` of this interpreter's environment (else the one on PATH)."""
    beside = Path(sys.executable).parent / name
    if beside.exists():
        return str(beside)
    found = shutil.which(name)
    if found is None:
        pytest.fail(f"console script {name} not installed: pip install -e '.[dev]'")
    return found


def clean_env(**extra: str) -> dict[str, str]:
    """The test process's environment without PRANET_* settings (so the developer's shell cannot leak in)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PRANET_") or k == "PRANET_DATA_DIR"}
    env.update(extra)
    return env
