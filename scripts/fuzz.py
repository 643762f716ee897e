"""A larger schemathesis run than the test suite's: ``python scripts/fuzz.py --examples 20000``.

Runs ``tests/service/test_service_fuzz.py`` (the same checks: no 5xx, documented statuses and
schemas) with more cases and fresh randomness. Without ``--url`` the test suite's fixture starts a
local ``pranet-serve``; with ``--url`` it fuzzes that server (``--api-key`` if it needs one).
Exit status: pytest's (0 = no failure found).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--examples", type=int, default=10000, help="generated /register cases (default 10000)")
    p.add_argument("--url", help="base URL of a running service (default: start one on loopback)")
    p.add_argument("--api-key", help="bearer key of that service")
    p.add_argument("--fixed", action="store_true", help="the suite's fixed (derandomized) cases instead of fresh ones")
    args = p.parse_args()
    env = dict(os.environ, PRANET_FUZZ_EXAMPLES=str(args.examples))
    if not args.fixed:
        env["PRANET_FUZZ_RANDOM"] = "1"
    if args.url:
        env["PRANET_FUZZ_URL"] = args.url.rstrip("/")
    if args.api_key:
        env["PRANET_FUZZ_API_KEY"] = args.api_key
    cmd = [sys.executable, "-m", "pytest", "tests/service/test_service_fuzz.py", "-q", "-s", "-p", "no:cacheprovider"]
    return subprocess.call(cmd, cwd=REPO, env=env)


if __name__ == "__main__":
    sys.exit(main())
