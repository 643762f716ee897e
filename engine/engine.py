"""``Engine``: the reward model and the ICP functions, built once, registering as a ``RegistrationConfig`` says.

The one way every consumer registers: the service (built at start-up, one per worker), ``pranet-eval``,
``pranet-bench`` and the scripts. Torch-free (onnxruntime and Open3D).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.typing as npt

from pranet.core.pipeline import register
from pranet.core.registration_config import POINT_TO_POINT, SERVICE_DEFAULT, IcpStage, RegistrationConfig
from pranet.core.registration_context import Scorer
from pranet.core.registration_types import GlobalMatchFn, IcpFn, PolishFn, Registration
from pranet.engine.global_match import global_matches
from pranet.engine.icp import make_icp
from pranet.engine.polish import make_polish

IcpFactory = Callable[..., IcpFn]  # (stages, window_unit=..., kernel=...) -> IcpFn


class Engine:
    """``scorer`` (a ``RewardModel``, or any ``core.pipeline.Scorer``) plus one ICP function per distinct list of
    stages and kernel, made by ``icp_factory`` (Open3D's, by default) on first use and kept (each caches its last
    target's preparation)."""

    def __init__(
        self,
        scorer: Scorer,
        icp_factory: IcpFactory = make_icp,
        global_match: GlobalMatchFn = global_matches,
        polish: PolishFn | None = None,
    ) -> None:
        self.scorer = scorer
        self._icp_factory = icp_factory
        self._global_match = global_match
        self._polish = polish if polish is not None else make_polish()
        self._icps: dict[tuple[tuple[IcpStage, ...], str, float | None], IcpFn] = {}
        self._lock = threading.Lock()

    @classmethod
    def load(cls, model_dir: str | Path | None = None, threads: int = 2, precision: str = "fp32") -> Engine:
        """The engine of a model directory (default: the shipped model)."""
        from pranet.engine.runtime import RewardModel

        return cls(RewardModel.load(model_dir, threads=threads, precision=precision))

    def icp(self, stages: tuple[IcpStage, ...], window_unit: str = "spacing", kernel: float | None = None) -> IcpFn:
        """The ICP function running ``stages`` (built once per distinct stages, window unit and kernel)."""
        with self._lock:
            key = (stages, window_unit, kernel)
            if key not in self._icps:
                self._icps[key] = self._icp_factory(stages, window_unit=window_unit, kernel=kernel)
            return self._icps[key]

    def warm_up(self, config: RegistrationConfig = SERVICE_DEFAULT) -> None:
        """Build ``config``'s ICP functions and register one small synthetic pair now, so that the first request
        does not pay for the imports and first calls of Open3D, scipy's KD-tree, KISS-Matcher and onnxruntime
        (half a second on our machine: a first request's preprocess took 485 ms against 75 for the next)."""
        self._refinement(config)
        u = np.random.default_rng(0).standard_normal((2000, 3))
        shape = u / np.linalg.norm(u, axis=1, keepdims=True) * [0.9, 0.5, 0.3] + [0.0, 0.0, 0.0]
        shape[:500] = shape[:500] * 0.3 + [0.5, 0.3, 0.1]  # a bump: no symmetry
        turned = shape @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).T  # 90°: the global match runs
        self.register(shape, turned, config.with_(rescue_restarts=False, rescue_window=None))

    def _refinement(self, config: RegistrationConfig) -> tuple[IcpFn | None, IcpFn | None]:
        icp = self.icp(config.icp_stages, kernel=config.icp_kernel) if config.refines else None
        wide = None
        if icp is not None and config.rescue_window is not None:
            wide = self.icp(((POINT_TO_POINT, config.rescue_window),), window_unit="extent")
        return icp, wide

    def register(
        self,
        source: npt.ArrayLike,
        target: npt.ArrayLike,
        config: RegistrationConfig = SERVICE_DEFAULT,
        rng: np.random.Generator | int = 0,
        deadline: float | None = None,
        seed: int = 0,
    ) -> Registration:
        """Register ``source`` onto ``target`` (any common units): ``T_target_source``, target ≈ R @ source + t.

        ``rng``: the generator of the resampling and the stochastic policies (or its seed); ``deadline``:
        ``time.monotonic()`` seconds, past which the agent raises ``AgentTimeout``; ``seed``: the global match's.
        """
        icp, wide = self._refinement(config)
        generator = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        return register(
            source,
            target,
            self.scorer,
            generator,
            config,
            icp=icp,
            rescue_icp=wide,
            deadline=deadline,
            global_match_fn=self._global_match,
            seed=seed,
            polish_fn=self._polish,
        )
