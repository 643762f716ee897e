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
``batch_score_fn(sources (B, N, 3), target) -> (B, A)`` call per step. A ``fine_score_fn`` of the same form scores
the steps of every scale after the first instead (the model's fine-phase call, ``RegistrationConfig.fine_matching``).

The walk (``walk_steps > 0``, beyond the paper): a network with the analytic reward layer computes its 24 rewards
in closed form from one estimated residual pose, so as long as that estimate stands the greedy steps toward it
need no network. ``pose_fn(sources (B, N, 3), target) -> (R_err (B, 3, 3), t_err (B, 3))`` gives the estimate
(the state of ``core.reward``); the loop keeps it as a goal pose per start, scores the actions toward it with
``core.reward.true_rewards`` (the same numbers the network's layer would give), and asks the network again
only when the walk has arrived (no step of the scale brings it nearer) or after ``walk_steps`` steps on one
estimate. A fresh estimate with no improving step ends the scale: what follows would be the paper's
oscillation about it. Without ``confirm_arrival`` an arrival ends the scale at once, with no fresh estimate: for
callers that refine the result by ICP anyway. ``walk_steps = 0`` is the paper's protocol, a network call per step.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from pranet.core.actions import DEFAULT_SCHEDULE, ActionTable
from pranet.core.reward import true_rewards
from pranet.core.se3 import Array, make_transform

ScoreFn = Callable[[Array, Array], npt.NDArray[np.floating]]
# batch_score_fn(sources (B, N, 3), target (M, 3)) -> rewards (B, A): the B rows are the same source point
# set in B poses (the starts of one registration), scored in one call.
BatchScoreFn = Callable[[Array, Array], npt.NDArray[np.floating]]
# batch_pose_fn(sources (B, N, 3), target (M, 3)) -> (R_err (B, 3, 3), t_err (B, 3)): the network's estimate of
# each row's residual pose (rotation still to apply about the row's centroid, translation still to add to it).
BatchPoseFn = Callable[[Array, Array], tuple[Array, Array]]
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
    pose_fn: BatchPoseFn | None = None,
    walk_steps: int = 0,
    confirm_arrival: bool = True,
    fine_score_fn: ScoreFn | None = None,
) -> AgentResult:
    """Register ``source: (N, 3)`` onto ``target: (M, 3)``; returns ``T_target_source`` and the trajectory.

    ``schedule[i]`` is the number of steps at scale ``i``. With ``early_stop``, a scale ends as soon
    as no action of it has a positive predicted reward. ``deadline`` (``time.monotonic()`` seconds):
    raise ``AgentTimeout`` once it has passed, checked before every step. ``pose_fn``, ``walk_steps`` and
    ``confirm_arrival``: the walk (module docstring); without ``pose_fn`` every step calls ``score_fn``.
    ``fine_score_fn``: scores the steps of every scale after the first (the fine phase) instead of ``score_fn``.
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
        pose_fn=pose_fn,
        walk_steps=walk_steps,
        confirm_arrival=confirm_arrival,
        fine_score_fn=None if fine_score_fn is None else batch_from_single(fine_score_fn),
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
    pose_fn: BatchPoseFn | None = None,
    walk_steps: int = 0,
    confirm_arrival: bool = True,
    fine_score_fn: BatchScoreFn | None = None,
) -> list[AgentResult]:
    """``run_agent`` from each of ``initial_transforms: (B, 4, 4)`` at once: one ``batch_score_fn`` call per step.

    Start ``b`` follows exactly the steps ``run_agent(..., initial_transform=initial_transforms[b])``
    takes with the same rewards (deterministic policy). With ``early_stop``, a start whose scale ended
    leaves the batch until the next scale (the batch shrinks). Stochastic policies draw from the one
    ``rng`` in start order at each step, so their draws differ from ``B`` separate runs. With ``pose_fn`` and
    ``walk_steps > 0`` the rows are scored by the walk (module docstring): ``batch_score_fn`` is not called.
    ``fine_score_fn`` (network calls only, not with the walk) scores the steps of every scale after the first.
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
    walk = PoseWalk(pose_fn, table, walk_steps, confirm_arrival) if pose_fn is not None and walk_steps > 0 else None
    if walk is not None and fine_score_fn is not None:
        raise ValueError("fine_score_fn scores network steps; the walk asks pose_fn instead")
    for scale, n_steps in enumerate(schedule):
        idx = table.indices_of_scale(scale)
        scorer = fine_score_fn if fine_score_fn is not None and scale > 0 else batch_score_fn
        active = list(range(len(T0)))
        for _ in range(n_steps):
            if not active:
                break
            if deadline is not None and time.monotonic() > deadline:
                raise AgentTimeout(f"registration exceeded its time limit after {max(steps)} steps")
            current = np.stack([centered @ R[b].T + c[b] for b in active])  # (B_active, N, 3)
            if walk is not None:
                rewards_all = walk.rewards(active, R, c, current, target, idx)
            else:
                rewards_all = np.asarray(scorer(current, target), dtype=np.float64)[:, idx]  # (B_active, A_s)
            still = []
            for b, rewards in zip(active, rewards_all, strict=True):
                # The walk's rewards are never all <= 0 on a stale estimate (it asks again first): a fresh one ends
                # the scale.
                if (early_stop or walk is not None) and rewards.max() <= 0.0:
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


class PoseWalk:
    """The walk's goals: per start, the pose the network's last estimate says the source should reach
    (``R_goal`` applied to the centred source, its centroid at ``c_goal``), and the steps taken since. ``confirm``:
    an arrival asks the network again (``False``: it ends the scale, for a caller that refines the result anyway)."""

    def __init__(self, pose_fn: BatchPoseFn, table: ActionTable, walk_steps: int, confirm: bool = True) -> None:
        self.pose_fn, self.table, self.walk_steps, self.confirm = pose_fn, table, walk_steps, confirm
        self.R_goal: dict[int, Array] = {}
        self.c_goal: dict[int, Array] = {}
        self.age: dict[int, int] = {}

    def toward(self, rows: Sequence[int], R: Array, c: Array, idx: Array) -> Array:
        """Exact rewards ``(len(rows), A_s)`` of the scale's actions ``idx`` toward each row's goal: the residual is
        ``R_goal @ R.T`` about the current centroid and ``c_goal - c``."""
        R_res = np.stack([self.R_goal[b] @ R[b].T for b in rows])
        t_res = np.stack([self.c_goal[b] - c[b] for b in rows])
        return true_rewards(R_res, t_res, self.table)[:, idx]

    def rewards(self, rows: Sequence[int], R: Array, c: Array, current: Array, target: Array, idx: Array) -> Array:
        """The rewards of ``rows`` (start indices; ``current`` holds their points in that order) at their poses
        ``R[b], c[b]``, asking the network again for rows without a goal, past ``walk_steps`` on one estimate, or
        (with ``confirm``) arrived: no action of the scale improves."""
        known = [i for i, b in enumerate(rows) if b in self.R_goal and self.age[b] < self.walk_steps]
        out = np.empty((len(rows), len(idx)))
        if known:  # scored once: these rewards are the answer unless the row is asked again below
            out[known] = self.toward([rows[i] for i in known], R, c, idx)
        arrived = [i for i in known if self.confirm and out[i].max() <= 0.0]
        ask = sorted(set(range(len(rows))) - set(known) | set(arrived))
        if ask:
            R_err, t_err = self.pose_fn(current[ask], target)
            for i, R_e, t_e in zip(ask, np.asarray(R_err, np.float64), np.asarray(t_err, np.float64), strict=True):
                b = rows[i]
                self.R_goal[b], self.c_goal[b], self.age[b] = R_e @ R[b], c[b] + t_e, 0
            out[ask] = self.toward([rows[i] for i in ask], R, c, idx)
        for b in rows:
            self.age[b] += 1
        return out


def batch_from_single(score_fn: ScoreFn) -> BatchScoreFn:
    """A ``BatchScoreFn`` that calls ``score_fn`` once per row (for scorers without a batched runtime)."""

    def score(sources: Array, target: Array) -> Array:
        return np.stack([np.asarray(score_fn(s, target), dtype=np.float64) for s in sources])

    return score


def oracle_pose_fn(T_gt: npt.ArrayLike, source: npt.ArrayLike) -> BatchPoseFn:
    """A perfect ``batch_pose_fn`` from the true ``T_gt`` (target = T_gt · source): each row's exact residual.
    Counts its calls (rows) in ``pose.calls``."""
    T_gt = np.asarray(T_gt, dtype=np.float64)
    source = np.asarray(source, dtype=np.float64)
    m = source.mean(axis=0)
    goal = T_gt[:3, :3] @ m + T_gt[:3, 3]
    calls = [0]

    def pose(currents: Array, _target: Array) -> tuple[Array, Array]:
        R_now = [_kabsch(source - m, cur - cur.mean(axis=0)) for cur in currents]
        calls[0] += len(currents)
        return np.stack([T_gt[:3, :3] @ R.T for R in R_now]), np.stack([goal - cur.mean(axis=0) for cur in currents])

    pose.calls = calls  # type: ignore[attr-defined]
    return pose


def _kabsch(a: Array, b: Array) -> Array:
    """The rotation taking centred ``a: (N, 3)`` onto centred ``b: (N, 3)``."""
    U, _, Vt = np.linalg.svd(a.T @ b)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    return Vt.T @ D @ U.T


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
        R_now = _kabsch(source - m, current - c)
        return true_rewards(T_gt[:3, :3] @ R_now.T, goal - c, table)

    return score
