"""States the greedy policy visits (beyond the paper): on-policy training states, as in DAgger.

The supervised states are drawn from fixed error distributions, but the agent is judged on the states its own greedy
steps lead to. Where the coarse phase stalls (its estimate says the source is nearly aligned while tens of degrees are
left; docs/DESIGN.md, "The clean failures are the coarse phase's"), those stalls are the states the training should
see, labelled with the truth. ``visit`` moves a training batch by a number of greedy steps of the network being
trained, and returns the batch with the error states and labels of where it arrived.

The batch layout is ``training.train.StateDataset``'s: ``(src, src_knn, tgt, tgt_knn, rewards, R_err, t_err)``, the
error about the (resampled) source's own centroid, so that ``R_err (p - c) + c + t_err`` is each point's true place.
An action ``(R_a, t_a)`` moves the source to ``R_a (p - c) + c + t_a``; the error left is ``(R_err R_aᵀ, t_err - t_a)``
(``core.reward``'s decoupled convention). The kNN graph of a rigidly moved cloud is the same graph, so it is kept.
"""

from __future__ import annotations

import numpy as np
import torch

from pranet.core.actions import ActionTable
from pranet.core.reward import true_rewards

Batch = tuple[torch.Tensor, ...]


def visit(net: torch.nn.Module, batch: Batch, table: ActionTable, steps: int, scale: int = 0) -> Batch:
    """``batch`` after ``steps`` greedy steps of ``net`` among the actions of ``scale`` (0: the coarse phase)."""
    src, src_knn, tgt, tgt_knn, _, R, t = batch
    idx = torch.as_tensor(table.indices_of_scale(scale))
    rotations = torch.as_tensor(table.rotations, dtype=src.dtype)  # (A, 3, 3)
    translations = torch.as_tensor(table.translations, dtype=src.dtype)  # (A, 3)
    training = net.training
    net.eval()  # the steps the exported (eval-mode) agent would take
    with torch.no_grad():
        for _ in range(steps):
            a = idx[net(src, src_knn, tgt, tgt_knn)[:, idx].argmax(dim=1)]  # (B,) the greedy action of each row
            R_a, t_a = rotations[a], translations[a]
            c = src.mean(dim=1, keepdim=True)
            src = (src - c) @ R_a.transpose(1, 2) + c + t_a.unsqueeze(1)
            R, t = R @ R_a.transpose(1, 2), t - t_a
    net.train(training)
    rewards = true_rewards(R.double().numpy(), t.double().numpy(), table).astype(np.float32)
    return src, src_knn, tgt, tgt_knn, torch.from_numpy(rewards), R, t


def visit_steps(rng: np.random.Generator, fraction: float, max_steps: int) -> int:
    """How many greedy steps one batch is moved by: 0 (a state as drawn) with probability ``1 - fraction``, else
    uniform in ``1..max_steps``, so that the batches cover every step of the phase."""
    if fraction <= 0.0 or rng.random() >= fraction:
        return 0
    return int(rng.integers(1, max_steps + 1))
