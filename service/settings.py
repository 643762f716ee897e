"""Service configuration, read once at the edge: environment variables ``PRANET_*``, overridden by CLI flags.

``pranet-serve`` writes the merged settings back into the environment before starting uvicorn, so
every worker process builds the same ``Settings()`` in ``create_app``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from pranet.core.wire import encoded_length

OPTIONS_BYTES = 64 * 1024  # the JSON around the two clouds: field names, the encoding tags, the options


def body_limit_for(max_points: int) -> int:
    """The body a request at the point limit needs: two clouds base64-encoded (16 bytes a point) and its options.

    A JSON list costs 8-60 bytes a point, so clouds near the limit must be sent base64-encoded (the client does
    above 5000 points)."""
    return 2 * encoded_length(max_points) + OPTIONS_BYTES


class Settings(BaseSettings):
    """All knobs of the HTTP service; env var = ``PRANET_`` + field name in upper case."""

    model_config = SettingsConfigDict(env_prefix="PRANET_", extra="ignore", frozen=True)

    model_dir: Path | None = Field(None, description="model directory written by pranet-export; None = the shipped one")
    host: str = Field("127.0.0.1", description="interface to bind")
    port: int = Field(8000, ge=0, le=65535, description="TCP port")
    workers: int = Field(1, ge=1, le=64, description="uvicorn worker processes (each loads the model once)")
    threads: int = Field(2, ge=1, le=256, description="onnxruntime intra-op threads per worker")
    precision: Literal["fp32", "int8"] = Field(
        "fp32", description="model graphs to run: fp32, or int8 (dynamic quantization; pranet-export --int8)"
    )
    max_points: int = Field(
        1_200_000,
        ge=3,
        description="most points per cloud (else 413); large clouds are voxel-downsampled by the pipeline, so this "
        "refuses only what cannot be handled at all",
    )
    max_list_points: int = Field(
        200_000,
        ge=3,
        description="most points per cloud sent as a JSON list [[x, y, z], ...] (else 413): a list costs about 3 us "
        "a point to parse, so larger clouds must use the base64 encoding (16 bytes a point, parsed 40x faster)",
    )
    max_body_bytes: int | None = Field(
        None,
        ge=1024,
        description="largest request body in bytes, refused with 413 before it is read (Content-Length) or as soon "
        "as it passes the limit (chunked); default: derived from max_points, two base64 clouds plus 64 kB of options "
        "(38.5 MB at 1,200,000 points)",
    )
    body_timeout_s: float = Field(
        20.0,
        gt=0,
        le=3600,
        description="time allowed to receive a request body (else 408), so a slow client cannot hold a "
        "registration slot; 20 s is 1.9 MB/s for a body at the default limit",
    )
    request_timeout_s: float = Field(30.0, gt=0, le=3600, description="deadline per registration, queueing included")
    max_concurrency: int = Field(2, ge=1, le=256, description="registrations computed at once per worker")
    max_queue: int = Field(4, ge=0, le=10_000, description="registrations waiting per worker; beyond: 503 at once")
    api_key: str | None = Field(None, description="when set, all routes but /health need 'Authorization: Bearer <key>'")
    cors_origins: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="allowed CORS origins, comma-separated or a JSON list; empty = CORS off"
    )
    shutdown_timeout_s: float = Field(30.0, ge=0, description="on SIGTERM, how long in-flight requests may finish")
    log_level: Literal["critical", "error", "warning", "info", "debug", "trace"] = Field(
        "info", description="uvicorn log level"
    )

    @field_validator("cors_origins", mode="before")
    @classmethod
    def _split_origins(cls, value: object) -> object:
        if isinstance(value, str):
            text = value.strip()
            if text.startswith("["):
                import json

                return json.loads(text)
            return [o.strip() for o in text.split(",") if o.strip()]
        return value

    @field_validator("api_key", "model_dir", mode="before")
    @classmethod
    def _empty_is_none(cls, value: object) -> object:
        return None if isinstance(value, str) and not value.strip() else value

    @property
    def body_limit_bytes(self) -> int:
        """``max_body_bytes``, or the limit derived from ``max_points`` when it is not set."""
        return self.max_body_bytes if self.max_body_bytes is not None else body_limit_for(self.max_points)

    def to_env(self) -> dict[str, str | None]:
        """``{PRANET_NAME: value}`` that rebuilds these settings in another process (None = unset)."""
        import json

        env: dict[str, str | None] = {}
        for name, value in self.model_dump().items():
            key = f"PRANET_{name.upper()}"
            if value is None:
                env[key] = None
            elif isinstance(value, list):
                env[key] = json.dumps(value)
            else:
                env[key] = str(value)
        return env
