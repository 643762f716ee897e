"""``pranet-serve``: verify the model, then run the HTTP service with uvicorn.

Settings come from ``PRANET_*`` environment variables; flags override them. The merged settings
are written back to the environment so that every uvicorn worker builds the same ``Settings()``.
A missing or corrupt model exits with status 1 and one line on stderr, before uvicorn starts.
"""

from __future__ import annotations

import argparse
import copy
import math
import os
import sys
from collections.abc import Sequence

from pydantic import ValidationError


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="pranet-serve",
        description="Serve PRANet point-cloud registration over HTTP (settings: PRANET_* env vars; flags override).",
    )
    p.add_argument("--host", help="interface to bind (PRANET_HOST, default 127.0.0.1)")
    p.add_argument("--port", type=int, help="TCP port (PRANET_PORT, default 8000)")
    p.add_argument("--model", dest="model_dir", help="model directory (PRANET_MODEL_DIR, default: the shipped model)")
    p.add_argument("--workers", type=int, help="worker processes (PRANET_WORKERS, default 1)")
    p.add_argument("--threads", type=int, help="onnxruntime threads per worker (PRANET_THREADS, default 2)")
    p.add_argument("--precision", choices=("fp32", "int8"), help="model graphs (PRANET_PRECISION, default fp32)")
    p.add_argument("--log-level", help="uvicorn log level (PRANET_LOG_LEVEL, default info)")
    return p.parse_args(argv)


def fail(message: str) -> int:
    print(f"pranet-serve: error: {message}", file=sys.stderr)
    return 1


def main(argv: Sequence[str] | None = None) -> int:
    # Open3D's ICP runs on OpenMP; busy-waiting worker threads collapse throughput when the cores are shared
    # (other workers, other processes): docs/PERFORMANCE.md. Read when libgomp loads, i.e. on the first ICP.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    args = parse_args(argv)
    from pranet.engine.runtime import ModelLoadError
    from pranet.service.settings import Settings
    from pranet.service.state import load_model

    overrides = {k: v for k, v in vars(args).items() if v is not None}
    try:
        settings = Settings(**overrides)
    except ValidationError as e:
        problems = "; ".join(f"{'.'.join(map(str, err['loc']))}: {err['msg']}" for err in e.errors())
        return fail(f"invalid settings: {problems}")
    # Fail fast, with one line, on a missing/corrupt model or an action-table mismatch.
    try:
        model = load_model(settings.model_dir, threads=1, precision=settings.precision)
    except ModelLoadError as e:
        return fail(" ".join(str(e).split()))
    info = model.info()
    del model
    print(f"pranet-serve: model {info['name']} {info['version']} (sha256 {info['sha256'][:12]}) verified", flush=True)

    for key, value in settings.to_env().items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value

    import uvicorn
    from uvicorn.config import LOGGING_CONFIG

    log_config = copy.deepcopy(LOGGING_CONFIG)
    log_config["loggers"]["pranet"] = {"handlers": ["default"], "level": settings.log_level.upper(), "propagate": False}
    try:
        uvicorn.run(
            "pranet.service.app:create_app",
            factory=True,
            host=settings.host,
            port=settings.port,
            workers=settings.workers,
            log_level=settings.log_level,
            log_config=log_config,
            timeout_graceful_shutdown=math.ceil(settings.shutdown_timeout_s),
        )
    except OSError as e:  # e.g. the port is taken
        return fail(str(e))
    return 0


if __name__ == "__main__":
    sys.exit(main())
