"""Wall time per named stage, kept out of the arithmetic: ``with timer.stage("icp"): ...``.

Stages nest, and the time is exclusive: while an inner stage runs, the outer one's clock is paused, so an ICP
call inside the agent's exit check counts as ``icp``, not as ``agent_steps``. Time outside every stage counts as
``other`` (the bookkeeping between stages), so the stages add up to the total exactly. One timer serves one
registration (not thread-safe).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

OTHER = "other"


class StageTimer:
    def __init__(self, stages: tuple[str, ...] = (), clock: Callable[[], float] = time.perf_counter) -> None:
        """``stages``: names reported (as 0) even when they never run, so every report has the same keys."""
        self._clock = clock
        self._start = clock()
        self._stack: list[str] = [OTHER]
        self._since = self._start  # when the innermost running stage last resumed
        self.ms: dict[str, float] = dict.fromkeys((*stages, OTHER), 0.0)

    def _charge(self, now: float) -> None:
        name = self._stack[-1]
        self.ms[name] = self.ms.get(name, 0.0) + (now - self._since) * 1e3
        self._since = now

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the block as ``name`` (added to earlier blocks of the same name)."""
        self._charge(self._clock())
        self._stack.append(name)
        self.ms.setdefault(name, 0.0)
        try:
            yield
        finally:
            self._charge(self._clock())
            self._stack.pop()

    def report(self) -> dict[str, float]:
        """Milliseconds per stage so far, and their ``total`` (the time since the timer was made)."""
        self._charge(self._clock())
        return {**self.ms, "total": (self._since - self._start) * 1e3}
