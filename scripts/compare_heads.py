"""Side-by-side reward MSE of network variants trained on the same states (docs/DESIGN.md).

    python scripts/compare_heads.py base,corr 3000 2     # variants, training states, epochs

``base``: pooled features + centroid offset; ``corr``: + soft-correspondence rotation features (the cpu
preset). Prints the validation MSE on the rotation and translation rewards after each epoch, with the
MSE of a zero predictor for scale.
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace

import numpy as np
import torch

from pranet.core.actions import build_action_table
from pranet.core.knn import knn_indices
from pranet.core.preprocess import resample
from pranet.model.network import RewardNet
from pranet.training.config import PRESETS
from pranet.training.data import data_dir, load_modelnet40, split_train_val
from pranet.training.samples import SETTINGS, StateDistribution, training_state


def make_states(shapes: np.ndarray, seed: int, n: int, table, states, n_points: int, k: int) -> list[torch.Tensor]:
    out = []
    for i in range(n):
        rng = np.random.default_rng([seed, i])
        st = training_state(shapes[i % len(shapes)], SETTINGS[i % 3], states, table, rng)
        s = resample(st.source, n_points, rng).astype(np.float32)
        t = resample(st.target, n_points, rng).astype(np.float32)
        out.append((s, knn_indices(s, k), t, knn_indices(t, k), st.rewards.astype(np.float32)))
    return [torch.from_numpy(np.stack(x)) for x in zip(*out, strict=True)]


def main() -> None:
    variants, n_train, epochs = sys.argv[1].split(","), int(sys.argv[2]), int(sys.argv[3])
    torch.set_num_threads(2)
    cfg = PRESETS["cpu"]
    table = build_action_table(cfg.scales)
    data = load_modelnet40(data_dir(), "train")
    split = split_train_val(data.labels, cfg.split_seed)
    states = StateDistribution(cfg.sampling.full, cfg.sampling.rotation, cfg.sampling.orientation_max_deg)
    n, k = cfg.net.n_points, cfg.net.k
    train = make_states(data.points[split.train], 1, n_train, table, states, n, k)
    val = make_states(data.points[split.val], 2, 384, table, states, n, k)
    rot = torch.from_numpy(table.rotation_indices)
    trans = torch.from_numpy(table.translation_indices)
    g = val[4]
    print(f"zero predictor: rotation {(g[:, rot] ** 2).mean():.4f} translation {(g[:, trans] ** 2).mean():.4f}")
    for name in variants:
        torch.manual_seed(0)
        net = RewardNet(replace(cfg.net, correspondence=name == "corr"), table)
        opt = torch.optim.AdamW(net.parameters(), 1e-3, weight_decay=1e-4)
        t0 = time.time()
        for epoch in range(epochs):
            perm = torch.randperm(n_train)
            for b in range(0, n_train - 15, 16):
                s, sk, t, tk, y = (x[perm[b : b + 16]] for x in train)
                loss = ((net(s, sk, t, tk) - y) ** 2).mean()
                opt.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
                opt.step()
            with torch.no_grad():
                net.eval()
                e = (net(*val[:4]) - g) ** 2
                net.train()
            print(
                f"{name} epoch {epoch} {time.time() - t0:.0f}s: val {e.mean():.4f} rotation {e[:, rot].mean():.4f} "
                f"translation {e[:, trans].mean():.4f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
