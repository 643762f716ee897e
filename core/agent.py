"""The greedy agent loop (paper, "Artificial Agent" and "Experiments").

The loop runs a schedule of step-size scales (default: 20 coarse steps, then 40 fine steps). At
each step only the current scale's actions are scored and applied. The runtime is injected as
``score_fn(source, target) -> rewards``: ``source: (N, 3)`` is the source in its current pose,
``target: (M, 3)`` never changes within a registration, ``rewards: (A,)`` follows the action table.
One ``score_fn`` serves one registration, so it may cache what depends on the target or on the
source's point set (its embedding, its kNN graph).

The estimate is kept decoupled (paper, "Application of actions"): ``source_now = R @ (x - m) + c``
with ``m`` the source centroid; rotations act on ``R`` (about the current centroid ``c``),
translations on ``c``. The returned transforms are ``T_target_source`` in the frame of the inputs.

``run_agent_batch`` runs the same loop from several start poses at once (the global mode), with one
``batch_score_fn(sources (B, N, 3), target) -> (B, A)`` call per step.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from pranet.core.actions import DEFAULT_SCHEDULE, ActionTable
from pranet.core.se3 import Array, make_transform

ScoreFn = Callable[[Array, Array], npt.NDArray[np.floating]]
# batch_score_fn(sources (B, N, 3), target (M, 3)) -> rewards (B, A): the B rows are the same source point
# set in B poses (the starts of one registration), scored in one call.
BatchScoreFn = Callable[[Array, Array], npt.NDArray[np.floating]]
POLICIES = ("deterministic", "stoch1", "stoch2")
STOCH1_PROBABILITIES = np.array([0.85, 0.15, 0.05])  # paper's numbers; they sum to 1.05, so normalised


class AgentTimeout(TimeoutError):
    """The agent loop ran past its deadline."""


@dataclass(frozen=True)
class AgentStep:
    step: int
    action: int  # index into the action table
    name: str
    transform: Array  # (4, 4) T_target_source after this step
    rewards: Array  # (A_scale,) predicted rewards of this scale's actions


@dataclass
class AgentResult:
    transform: Array  # (4, 4) T_target_source
    steps: list[AgentStep] = field(default_factory=list)
    stopped_early: list[int] = field(default_factory=list)  # steps at which a scale was cut short


def choose_action(rewards: Array, policy: str, rng: np.random.Generator | None) -> int:
    """Index into ``rewards: (A_scale,)`` by ``policy`` (paper, "Stochasticity of the policy")."""
    if policy == "deterministic":
        return int(np.argmax(rewards))
    if rng is None:
        raise ValueError(f"policy {policy!r} needs an explicit rng")
    if policy == "stoch1":
        top = np.argsort(-rewards)[: len(STOCH1_PROBABILITIES)]
        p = STOCH1_PROBABILITIES[: len(top)]
        return int(rng.choice(top, p=p / p.sum()))
    if policy == "stoch2":
        positive = np.flatnonzero(rewards > 0)
        return int(rng.choice(positive)) if len(positive) else int(np.argmax(rewards))
    raise ValueError(f"unknown policy {policy!r}; choose from {POLICIES}")


def run_agent(
    source: npt.ArrayLike,
    target: npt.ArrayLike,
    score_fn: ScoreFn,
    table: ActionTable,
    schedule: Sequence[int] = DEFAULT_SCHEDULE,
    policy: str = "deterministic",
    rng: np.random.Generator | None = None,
    early_stop: bool = False,
    initial_transform: npt.ArrayLike | None = None,
    deadline: float | None = None,
) -> AgentResult:
    """Register ``source: (N, 3)`` onto ``target: (M, 3)``; returns ``T_target_source`` and the trajectory.

    ``schedule[i]`` is the number of steps at scale ``i``. With ``early_stop``, a scale ends as soon
    as no action of it has a positive predicted reward. ``deadline`` (``time.monotonic()`` seconds):
    raise ``AgentTimeout`` once it has passed, checked before every step.
    """
    T0 = np.eye(4) if initial_transform is None else np.asarray(initial_transform, dtype=np.float64)
    # The batched loop with one start; the single score_fn is called once per step as before.
    return run_agent_batch(
        source,
        target,
        batch_from_single(score_fn),
        table,
        T0[None],
        schedule,
        policy=policy,
        rng=rng,
        early_stop=early_stop,
        deadline=deadline,
    )[0]


def run_agent_batch(
    source: npt.ArrayLike,
    target: npt.ArrayLike,
    batch_score_fn: BatchScoreFn,
    table: ActionTable,
    initial_transforms: npt.ArrayLike,
    schedule: Sequence[int] = DEFAULT_SCHEDULE,
    policy: str = "deterministic",
    rng: np.random.Generator | None = None,
    early_stop: bool = False,
    deadline: float | None = None,
) -> list[AgentResult]:
    """``run_agent`` from each of ``initial_transforms: (B, 4, 4)`` at once: one ``batch_score_fn`` call per step.

    Start ``b`` follows exactly the steps ``run_agent(..., initial_transform=initial_transforms[b])``
    takes with the same rewards (deterministic policy). With ``early_stop``, a start whose scale ended
    leaves the batch until the next scale (the batch shrinks). Stochastic policies draw from the one
    ``rng`` in start order at each step, so their draws differ from ``B`` separate runs.
    """
    if len(schedule) != len(table.scales):
        raise ValueError(f"schedule has {len(schedule)} phases but the action table has {len(table.scales)} scales")
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    T0 = np.asarray(initial_transforms, dtype=np.float64).reshape(-1, 4, 4)  # (B, 4, 4)
    m = source.mean(axis=0)
    centered = source - m  # (N, 3)
    R = T0[:, :3, :3].copy()  # (B, 3, 3)
    c = np.stack([T[:3, :3] @ m + T[:3, 3] for T in T0])  # (B, 3) where each start's source centroid is now
    results = [AgentResult(transform=T.copy()) for T in T0]
    steps = [0] * len(T0)
    for scale, n_steps in enumerate(schedule):
        idx = table.indices_of_scale(scale)
        active = list(range(len(T0)))
        for _ in range(n_steps):
            if not active:
                break
            if deadline is not None and time.monotonic() > deadline:
                raise AgentTimeout(f"registration exceeded its time limit after {max(steps)} steps")
            current = np.stack([centered @ R[b].T + c[b] for b in active])  # (B_active, N, 3)
            rewards_all = np.asarray(batch_score_fn(current, target), dtype=np.float64)[:, idx]  # (B_active, A_s)
            still = []
            for b, rewards in zip(active, rewards_all, strict=True):
                if early_stop and rewards.max() <= 0.0:
                    results[b].stopped_early.append(steps[b])
                    continue
                a = int(idx[choose_action(rewards, policy, rng)])
                R[b] = table.rotations[a] @ R[b]
                c[b] = c[b] + table.translations[a]
                T = make_transform(R[b], c[b] - R[b] @ m)
                results[b].steps.append(AgentStep(steps[b], a, table.names[a], T, rewards))
                steps[b] += 1
                still.append(b)
            active = still
    for b, result in enumerate(results):
        result.transform = make_transform(R[b], c[b] - R[b] @ m)
    return results


def batch_from_single(score_fn: ScoreFn) -> BatchScoreFn:
    """A ``BatchScoreFn`` that calls ``score_fn`` once per row (for scorers without a batched runtime)."""

    def score(sources: Array, target: Array) -> Array:
        return np.stack([np.asarray(score_fn(s, target), dtype=np.float64) for s in sources])

    return score


def oracle_score_fn(T_gt: npt.ArrayLike, source: npt.ArrayLike, table: ActionTable) -> ScoreFn:
    """A perfect ``score_fn`` from the true ``T_gt`` (target = T_gt · source): the exact rewards.

    For tests and for the upper bound of the MDP. ``source`` is the original source ``(N, 3)``.
    """
    from pranet.core.reward import true_rewards

    T_gt = np.asarray(T_gt, dtype=np.float64)
    source = np.asarray(source, dtype=np.float64)
    m = source.mean(axis=0)
    goal = T_gt[:3, :3] @ m + T_gt[:3, 3]  # where the source centroid must go

    def score(current: Array, _target: Array) -> Array:
        # Current pose from the moved points: R_now by Kabsch on centered points, c = their mean.
        c = current.mean(axis=0)
        H = (source - m).T @ (current - c)
        U, _, Vt = np.linalg.svd(H)
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
        R_now = Vt.T @ D @ U.T
        return true_rewards(T_gt[:3, :3] @ R_now.T, goal - c, table)

    return score
