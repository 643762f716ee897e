"""The README's figures on the example pair come from ``scripts/readme_figures.py``: run it (its own
``pranet-serve``, the shipped model) and find every line the README quotes from it in what it prints.

When the pipeline, the confidence or the model changes, this fails until the README is regenerated with the
command it names. Latency lines are not quoted in that block: they depend on the machine.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
pytest.importorskip("open3d")


def quoted_block() -> list[str]:
    """The ```text block that follows the README's mention of the script."""
    readme = (REPO / "README.md").read_text()
    match = re.search(r"scripts/readme_figures\.py`[^`]*?prints them.*?```text\n(.*?)```", readme, re.S)
    assert match, "README: no ```text block of scripts/readme_figures.py's lines"
    return [line for line in match.group(1).splitlines() if line.strip()]


@pytest.mark.slow
def test_readme_quotes_what_the_script_prints() -> None:
    out = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "readme_figures.py"), "--repeats", "1", "--scans", "none"],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=REPO,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    printed = out.stdout.splitlines()
    assert any(line.startswith("latency (median of 1") for line in printed), out.stdout
    true_motion = next(line for line in printed if line.startswith("pair: "))
    assert "true motion 34.3° and 53 mm" in true_motion  # examples/bunny/T_target_source.txt
    stale = [line for line in quoted_block() if line not in printed]
    assert not stale, (
        "README figures are stale; regenerate with `python scripts/readme_figures.py`.\n"
        f"README quotes: {stale}\nthe script printed:\n{out.stdout}"
    )
