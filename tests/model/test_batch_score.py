"""RewardModel.batch_score_fn (the global mode's one call per step) against score_fn per start."""

import numpy as np
import pytest

from pranet.core.se3 import apply_transform
from pranet.core.starts import start_rotations, start_transforms

pytest.importorskip("onnxruntime")


def test_batched_rows_equal_single_calls():
    from pranet.engine.runtime import RewardModel

    model = RewardModel.load(threads=1)
    rng = np.random.default_rng(0)
    source = rng.normal(size=(model.n_points, 3)) * [0.5, 0.3, 0.2]
    target = rng.normal(size=(model.n_points, 3)) * [0.5, 0.3, 0.2]
    starts = start_transforms(start_rotations(5), source.mean(axis=0), target.mean(axis=0))
    moved = np.stack([apply_transform(T, source) for T in starts])  # (5, N, 3)
    batched = model.batch_score_fn(target)
    single = model.score_fn(target)
    out = batched(moved, target)
    assert out.shape == (5, len(model.table))
    # float32: a batch and a single row take different kernel paths, and the reward layer's angle differences of
    # the fine scale amplify the rounding (up to 3e-5 measured); a row scored for another start is off by ~0.1.
    for b in range(5):
        np.testing.assert_allclose(out[b], single(moved[b], target), rtol=1e-4, atol=1e-4)
    # a smaller batch later (early stop shrinks it) reuses the same graph
    np.testing.assert_allclose(batched(moved[2:4], target), out[2:4], rtol=1e-4, atol=1e-4)
