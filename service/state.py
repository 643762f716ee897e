"""What one worker process holds: the settings, the engine (model and ICP, built once), the admission gate."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import anyio

from pranet.engine.engine import Engine
from pranet.engine.runtime import ModelLoadError, RewardModel, default_model_dir
from pranet.service.registration import RequestError
from pranet.service.settings import Settings

log = logging.getLogger("pranet.service")


def load_model(model_dir: Path | None, threads: int, precision: str = "fp32") -> RewardModel:
    """``RewardModel.load`` with every failure turned into a one-line ``ModelLoadError``."""
    where = model_dir or default_model_dir()
    try:
        return RewardModel.load(model_dir, threads=threads, precision=precision)
    except ModelLoadError:
        raise
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as e:  # a card with missing/mangled fields
        raise ModelLoadError(f"invalid model card in {where}: {type(e).__name__}: {e}") from e
    except OSError as e:
        raise ModelLoadError(f"cannot read model directory {where}: {e}") from e


class Admission:
    """Non-blocking admission: at most ``max_concurrency`` computing plus ``max_queue`` waiting, else 503 at once.

    Used from the event loop only (single thread), so the counter needs no lock; the computing
    slots are an anyio ``CapacityLimiter`` handed to ``to_thread.run_sync``.
    """

    def __init__(self, max_concurrency: int, max_queue: int):
        self.max_concurrency = max_concurrency
        self.max_queue = max_queue
        self.in_flight = 0
        self.limiter = anyio.CapacityLimiter(max_concurrency)

    @contextmanager
    def admit(self) -> Iterator[None]:
        if self.in_flight >= self.max_concurrency + self.max_queue:
            raise RequestError(503, "server at capacity: too many registrations in progress; retry shortly")
        self.in_flight += 1
        try:
            yield
        finally:
            self.in_flight -= 1


class ServiceState:
    """Stored on ``app.state.service`` by the lifespan."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self.engine: Engine | None = None
        self.model_error: str | None = "model not loaded yet"
        self.admission = Admission(settings.max_concurrency, settings.max_queue)

    @property
    def model(self) -> RewardModel | None:
        return self.engine.scorer if self.engine is not None else None  # type: ignore[return-value]

    def load(self) -> None:
        """Load the model and build and warm the engine (Open3D, KISS-Matcher, scipy: loaded now, not in a request)."""
        try:
            self.engine = Engine(load_model(self.settings.model_dir, self.settings.threads, self.settings.precision))
            self.engine.warm_up()
            self.model_error = None
            log.info("model %s loaded", self.require_model().info())
        except ModelLoadError as e:
            self.engine, self.model_error = None, str(e)
            log.error("model not loaded: %s", e)

    def require_engine(self) -> Engine:
        if self.engine is None:
            raise RequestError(503, f"model not loaded: {self.model_error}")
        return self.engine

    def require_model(self) -> RewardModel:
        return self.require_engine().scorer  # type: ignore[return-value]
