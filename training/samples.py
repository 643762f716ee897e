"""Registration problems built from ModelNet40 shapes: the three test settings and the training states.

Settings (fixed, so that results compare):

- ``clean``: source = the shape's points; target = ``T_gt · source``, shuffled.
- ``noisy``: source and target are independent random subsets of half the points (512 of 1024, the
  paper's ratio of 1024 of 2048); each gets N(0, 0.01²) noise clipped to ±0.05 (RPMNet protocol).
- ``partial``: as noisy, then each cloud keeps the 70 % of its points farthest along a random direction.

``T_gt``: isotropic rotation up to 60°, translation uniform in [-0.5, 0.5]³ (paper, "Clean Dataset").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pranet.core.actions import ActionTable
from pranet.core.reward import point_rewards, true_rewards
from pranet.core.sampling import sample_rotations, sample_translations, sample_unit_vectors
from pranet.core.se3 import Array, apply_transform, make_transform

SETTINGS = ("clean", "noisy", "partial")
NOISE_STD = 0.01
NOISE_CLIP = 0.05
SUBSET_FRACTION = 0.5
KEEP_FRACTION = 0.7


def jitter(points: Array, rng: np.random.Generator) -> Array:
    return points + np.clip(rng.normal(0.0, NOISE_STD, points.shape), -NOISE_CLIP, NOISE_CLIP)


def crop(points: Array, rng: np.random.Generator, keep: float = KEEP_FRACTION) -> Array:
    """Keep the ``keep`` fraction of points farthest along a uniform random direction (a random plane)."""
    d = sample_unit_vectors(rng, 1)[0]
    n_keep = int(round(keep * len(points)))
    return points[np.argsort(points @ d)[-n_keep:]]


def observe(shape: Array, setting: str, rng: np.random.Generator) -> tuple[Array, Array]:
    """Two observations of one shape in its own frame: ``(source (N, 3), target (M, 3))``."""
    shape = np.asarray(shape, dtype=np.float64)
    if setting == "clean":
        return shape, shape[rng.permutation(len(shape))]
    if setting not in SETTINGS:
        raise ValueError(f"unknown setting {setting!r}; choose from {SETTINGS}")
    n = int(round(SUBSET_FRACTION * len(shape)))
    src = jitter(shape[rng.choice(len(shape), n, replace=False)], rng)
    tgt = jitter(shape[rng.choice(len(shape), n, replace=False)], rng)
    if setting == "partial":
        src, tgt = crop(src, rng), crop(tgt, rng)
    return src, tgt


@dataclass(frozen=True)
class Pair:
    """A test problem: ``target ≈ T_gt · source``; ``clean_source`` is the complete clean shape."""

    source: Array
    target: Array
    clean_source: Array
    T_gt: Array


def make_pair(
    shape: Array,
    setting: str,
    rng: np.random.Generator,
    max_angle_deg: float = 60.0,
    max_translation: float = 0.5,
    rotation: str = "isotropic",
) -> Pair:
    src, tgt = observe(shape, setting, rng)
    T_gt = make_transform(
        sample_rotations(rng, rotation, np.deg2rad(max_angle_deg), 1)[0],
        sample_translations(rng, max_translation, 1)[0],
    )
    return Pair(source=src, target=apply_transform(T_gt, tgt), clean_source=np.asarray(shape, np.float64), T_gt=T_gt)


def pair_rng(seed: int, setting: str, index: int) -> np.random.Generator:
    """The generator of test pair ``index``: every method sees the same pairs."""
    return np.random.default_rng([seed, SETTINGS.index(setting), index])


@dataclass(frozen=True)
class StateDistribution:
    """How training states are drawn: ``components = ((max_angle_deg, max_translation, weight), ...)``."""

    components: tuple[tuple[float, float, float], ...]
    rotation: str = "isotropic"
    orientation_max_deg: float = 0.0

    def pick(self, rng: np.random.Generator) -> int:
        """The index of a component, drawn by weight."""
        w = np.array([c[2] for c in self.components], dtype=np.float64)
        return int(rng.choice(len(w), p=w / w.sum()))

    def draw(self, rng: np.random.Generator, component: int | None = None) -> tuple[Array, Array]:
        """One error state ``(R_err (3, 3), t_err (3,))`` from ``component``, or from one drawn by weight."""
        angle, trans, _ = self.components[self.pick(rng) if component is None else component]
        return (
            sample_rotations(rng, self.rotation, np.deg2rad(angle), 1)[0],
            sample_translations(rng, trans, 1)[0],
        )


@dataclass(frozen=True)
class TrainingState:
    source: Array  # (Ns, 3) in its current pose
    target: Array  # (Nt, 3)
    rewards: Array  # (A,) labels
    R_err: Array  # (3, 3) rotation still to apply about the source centroid
    t_err: Array  # (3,) translation still to apply to the source centroid


def training_state(
    shape: Array,
    setting: str,
    states: StateDistribution,
    table: ActionTable,
    rng: np.random.Generator,
    reward: str = "se3",
    component: int | None = None,
) -> TrainingState:
    """One supervised sample: the source in its current pose, the target, and the rewards.

    The pair is first placed in a random common orientation ``Q`` (rewards depend only on the error
    state, so this is exact augmentation and covers the poses the agent visits mid-trajectory). Then
    the source is moved off its true pose by the inverse of the error ``(R_err, t_err)``, defined
    about its centroid, so that applying ``R_err`` about the centroid and adding ``t_err`` aligns it.
    """
    src, tgt = observe(shape, setting, rng)
    Q = sample_rotations(rng, "isotropic", np.deg2rad(states.orientation_max_deg), 1)[0]
    src_true, tgt = src @ Q.T, tgt @ Q.T
    R_err, t_err = states.draw(rng, component)
    m_true = src_true.mean(axis=0)
    source = (src_true - m_true) @ R_err + (m_true - t_err)  # R_err.T applied to rows: (x - m) @ R_err
    if reward == "se3":
        rewards = true_rewards(R_err, t_err, table)
    else:
        clean = np.asarray(shape, np.float64) @ Q.T
        clean_rel = (clean - m_true) @ R_err  # clean shape in the source's current pose, relative to c
        rewards = point_rewards(clean_rel, R_err, t_err, table, kind=reward)
    return TrainingState(source, tgt, rewards, R_err, t_err)


def curriculum_states(
    epoch: int,
    epochs: int,
    curriculum: str,
    full: Sequence[tuple[float, float, float]],
    small: tuple[float, float],
    fraction: float,
) -> tuple[tuple[float, float, float], ...]:
    """The state components of ``epoch`` (paper, "Clean Dataset" and "Curriculum learning").

    ``paper``: the first ``fraction`` of the epochs (70 of 1300) use only ``small`` = (10°, 0.5/7),
    the rest ``full``. ``uniform``: always ``full``. ``adhoc``: ``small`` and ``full`` 50/50 throughout.
    """
    small_c = (small[0], small[1], 1.0)
    if curriculum == "paper":
        return (small_c,) if epoch < max(1, round(fraction * epochs)) else tuple(full)
    if curriculum == "uniform":
        return tuple(full)
    if curriculum == "adhoc":
        total = sum(c[2] for c in full)
        return (*full, (small[0], small[1], total))
    raise ValueError(f"unknown curriculum {curriculum!r}")
