"""Training and inference speed of network candidates in torch (docs/DESIGN.md, "The cpu preset").

    python scripts/time_candidates.py

Per candidate: training samples/s (B 16, forward + backward + AdamW step, random inputs) and the time
of one agent step (B 1: embed the source, score against a cached target embedding).
"""

from __future__ import annotations

import time
from dataclasses import replace

import torch

from pranet.core.actions import build_action_table
from pranet.model.config import CPU_NET, NetConfig
from pranet.model.network import RewardNet

CANDIDATES = {
    "N 256, 64/64/128 -> 128, 1 cross block": replace(CPU_NET, n_points=256),
    "N 384": replace(CPU_NET, n_points=384),
    "N 512": replace(CPU_NET, n_points=512),
    "N 512, no Transformer": replace(CPU_NET, n_points=512, blocks=0),
    "N 512, 64/64/128/256 -> 256": replace(
        CPU_NET, n_points=512, edge_widths=(64, 64, 128, 256), emb_dim=256, ff_dim=512
    ),
    "shipped (N 256, maxmean, correspondence)": replace(CPU_NET, n_points=256, pool="maxmean", correspondence=True),
}


def time_candidate(cfg: NetConfig, batch: int = 16) -> tuple[float, float]:
    torch.manual_seed(0)
    net = RewardNet(cfg, build_action_table())
    opt = torch.optim.AdamW(net.parameters(), 1e-3)
    x, y = torch.randn(batch, cfg.n_points, 3), torch.randn(batch, cfg.n_points, 3)
    idx = torch.randint(0, cfg.n_points, (batch, cfg.n_points, cfg.k))
    for i in range(4):  # the first iteration is a warm-up
        if i == 1:
            t0 = time.perf_counter()
        loss = net(x, idx, y, idx).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    train = 3 * batch / (time.perf_counter() - t0)
    net.eval()
    with torch.no_grad():
        tf, tc = net.embed(y[:1], idx[:1])
        t0 = time.perf_counter()
        for _ in range(20):
            net.score(*net.embed(x[:1], idx[:1]), tf, tc, x[:1], y[:1])
        step_ms = (time.perf_counter() - t0) / 20 * 1e3
    return train, step_ms


def main() -> None:
    print(f"{'candidate':45s} {'train samples/s':>16s} {'ms per step':>12s}")
    for name, cfg in CANDIDATES.items():
        train, step = time_candidate(cfg)
        print(f"{name:45s} {train:16.1f} {step:12.2f}")


if __name__ == "__main__":
    main()
