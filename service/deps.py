"""FastAPI dependencies: the worker's state and its engine, for the routes' signatures."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from pranet.engine.engine import Engine
from pranet.engine.runtime import RewardModel
from pranet.service.state import ServiceState


def get_state(request: Request) -> ServiceState:
    return request.app.state.service


StateDep = Annotated[ServiceState, Depends(get_state)]


def get_engine(state: StateDep) -> Engine:
    """The engine, or 503 while the model is not loaded."""
    return state.require_engine()


def get_model(state: StateDep) -> RewardModel:
    """The loaded reward model, or 503."""
    return state.require_model()


EngineDep = Annotated[Engine, Depends(get_engine)]
ModelDep = Annotated[RewardModel, Depends(get_model)]
