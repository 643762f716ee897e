"""``pranet-train``: supervised regression of the action rewards (paper, "Loss function").

``Loss = 1/|A| ||g - h||²`` (+ weight decay in the optimiser) on i.i.d. states. Writes, under
``--out``: ``config.json``, ``last.pt`` / ``best.pt`` (every epoch), ``log.csv``, TensorBoard
events and ``summary.json``. ``--resume`` continues from ``last.pt``. Runs under
``torchrun --nproc_per_node=K`` (DDP; gloo on CPU, nccl on GPU).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, Dataset

from pranet.core.actions import ActionTable, build_action_table
from pranet.core.knn import knn_indices
from pranet.core.preprocess import resample
from pranet.model.network import RewardNet
from pranet.training.config import PRESETS, TrainConfig, parse_override
from pranet.training.data import Splits, data_dir, load_modelnet40, split_train_val
from pranet.training.samples import StateDistribution, curriculum_states, training_state
from pranet.training.visited import visit, visit_steps


def _setting_weights(settings: Sequence[tuple[str, float]]) -> tuple[tuple[str, ...], np.ndarray]:
    names, weights = zip(*settings, strict=True)
    return names, np.array(weights, dtype=np.float64) / sum(weights)


class StateDataset(Dataset):
    """Sample ``i`` of an epoch: a fresh random state of shape ``shapes[order[i]]``, seeded by (seed, epoch, i)."""

    def __init__(
        self,
        shapes: np.ndarray,
        cfg: TrainConfig,
        table: ActionTable,
        states: StateDistribution,
        seed_key: tuple[int, ...],
    ) -> None:
        self.shapes = shapes
        self.cfg = cfg
        self.table = table
        self.states = states
        self.seed_key = seed_key
        self.far = _setting_weights(cfg.sampling.settings)
        self.near = _setting_weights(cfg.sampling.near_settings) if cfg.sampling.near_settings else None
        self.near_max_deg = cfg.sampling.near_max_deg

    def setting_and_component(self, rng: np.random.Generator) -> tuple[str, int | None]:
        """The setting of one state and, with ``near_settings``, its error component (else drawn later)."""
        component = None
        names, p = self.far
        if self.near is not None:  # the component first: it decides which setting weights apply
            component = self.states.pick(rng)
            if self.states.components[component][0] <= self.near_max_deg:
                names, p = self.near
        return names[int(rng.choice(len(names), p=p))], component

    def __len__(self) -> int:
        return len(self.shapes)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, ...]:
        rng = np.random.default_rng([*self.seed_key, i])
        setting, component = self.setting_and_component(rng)
        state = training_state(
            self.shapes[i], setting, self.states, self.table, rng, self.cfg.sampling.reward, component
        )
        src, tgt, rewards = state.source, state.target, state.rewards
        n, k = self.cfg.net.n_points, self.cfg.net.k
        src, tgt = resample(src, n, rng).astype(np.float32), resample(tgt, n, rng).astype(np.float32)
        # The residual pose about the resampled source's centroid c' (the network's): the source goes to
        # R_err (p - c) + c + t_err with c the full source's centroid, so c' must move by t' below.
        c = state.source.mean(axis=0)
        c_resampled = src.mean(axis=0, dtype=np.float64)
        t_resampled = state.R_err @ (c_resampled - c) + c + state.t_err - c_resampled
        return (
            torch.from_numpy(src),
            torch.from_numpy(knn_indices(src, k)),
            torch.from_numpy(tgt),
            torch.from_numpy(knn_indices(tgt, k)),
            torch.from_numpy(rewards.astype(np.float32)),
            torch.from_numpy(state.R_err.astype(np.float32)),
            torch.from_numpy(t_resampled.astype(np.float32)),
        )


def pose_error(R_hat: torch.Tensor, t_hat: torch.Tensor, R: torch.Tensor, t: torch.Tensor, points: torch.Tensor):
    """Mean distance of the source points ``(B, N, 3)`` placed by the estimate from their true places (RPMNet's
    loss), both poses about the points' centroid -> ``(B,)``."""
    centred = points - points.mean(dim=1, keepdim=True)
    diff = centred @ (R_hat - R).transpose(1, 2) + (t_hat - t).unsqueeze(1)  # (B, N, 3)
    return diff.norm(dim=-1).mean(dim=1)


# A point overlaps the other cloud when its true place is within this many of that cloud's median point spacings of
# a point of it: the two clouds are independent samples, so a point of the shared part has a neighbour about a
# spacing away, and a cropped-away one only beyond the cut.
OVERLAP_SPACINGS = 2.0


def overlap_labels(
    src: torch.Tensor, tgt: torch.Tensor, R: torch.Tensor, t: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Whether each point of ``src: (B, N, 3)`` (at its true place: ``R (p - c) + c + t``, ``c`` its centroid) and
    of ``tgt: (B, M, 3)`` has a counterpart in the other cloud -> float ``(B, N)``, ``(B, M)``."""
    c = src.mean(dim=1, keepdim=True)
    placed = (src - c) @ R.transpose(1, 2) + c + t.unsqueeze(1)
    d = torch.cdist(placed, tgt)  # (B, N, M)
    own = torch.cdist(tgt, tgt) + torch.eye(tgt.shape[1]) * 1e9  # (B, M, M), no point its own neighbour
    spacing = own.amin(dim=2).median(dim=1).values.view(-1, 1)  # (B, 1)
    near = OVERLAP_SPACINGS * spacing
    return (d.amin(dim=2) < near).float(), (d.amin(dim=1) < near).float()


def batch_loss(
    net: torch.nn.Module, batch: tuple[torch.Tensor, ...], cfg: TrainConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(loss (), per-sample reward MSE (B,))``: ``reward_weight`` × reward MSE (paper, "Loss function")
    + ``pose_weight`` × the pose error of the analytic head's estimate (beyond the paper) + ``overlap_weight`` × the
    overlap head's binary cross-entropy (mean of the two clouds')."""
    src, src_knn, tgt, tgt_knn, g, R, t = batch
    core = net.module if hasattr(net, "module") else net
    if cfg.optim.pose_weight and getattr(core, "analytic", None) is not None:
        R_hat, t_hat, _, rewards = core.pose_and_rewards(src, src_knn, tgt, tgt_knn)
        error = pose_error(R_hat, t_hat, R, t, src)  # (B,)
        if cfg.optim.pose_loss == "relative":
            # Each state's error relative to its own size (the identity's error, + 0.01 so that aligned states
            # stay finite): a 2° state weighs as much as a 60° one, which the fine phase's precision needs.
            eye = torch.eye(3).expand_as(R)
            error = error / (pose_error(eye, torch.zeros_like(t), R, t, src).detach() + 0.01)
        pose = error.mean()
    else:
        rewards, pose = net(src, src_knn, tgt, tgt_knn), torch.zeros(())
    mse = ((rewards - g) ** 2).mean(dim=1)
    loss = cfg.optim.reward_weight * mse.mean() + cfg.optim.pose_weight * pose
    head = getattr(core.correspondence, "overlap_logits", None) if cfg.optim.overlap_weight else None
    if head is not None:  # set by the forward pass above
        labels = overlap_labels(src, tgt, R, t)
        bce = [torch.nn.functional.binary_cross_entropy_with_logits(o, y) for o, y in zip(head, labels, strict=True)]
        loss = loss + cfg.optim.overlap_weight * (bce[0] + bce[1]) / 2
    return loss, mse.detach()


def build_optimizer(
    net: torch.nn.Module, cfg: TrainConfig
) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LRScheduler]:
    o = cfg.optim
    if o.optimizer == "sgd":
        opt: torch.optim.Optimizer = torch.optim.SGD(
            net.parameters(), lr=o.lr, momentum=o.momentum, weight_decay=o.weight_decay
        )
    elif o.optimizer == "adamw":
        opt = torch.optim.AdamW(net.parameters(), lr=o.lr, weight_decay=o.weight_decay)
    else:
        raise ValueError(f"unknown optimizer {o.optimizer!r}")
    if o.schedule == "step":
        sched: torch.optim.lr_scheduler.LRScheduler = torch.optim.lr_scheduler.MultiStepLR(
            opt, list(o.milestones), o.gamma
        )
    elif o.schedule == "cosine":
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=o.epochs, eta_min=o.lr * 0.01)
    else:
        raise ValueError(f"unknown schedule {o.schedule!r}")
    return opt, sched


def warm_start(net: torch.nn.Module, path: Path, rank: int) -> None:
    """Copy every parameter of the checkpoint ``path`` whose name and shape match ``net``'s (the embedding of
    an earlier run); the rest keep their fresh initialisation."""
    state = torch.load(path, map_location="cpu", weights_only=False)["model"]
    own = net.state_dict()
    shared = {k: v for k, v in state.items() if k in own and own[k].shape == v.shape}
    net.load_state_dict(shared, strict=False)
    if rank == 0:
        print(f"warm start from {path}: {len(shared)} of {len(own)} tensors")


def resolve_config(args: argparse.Namespace) -> TrainConfig:
    cfg = PRESETS[args.preset]
    for item in args.set or []:
        cfg = parse_override(cfg, item)
    if args.epochs is not None:
        cfg = replace(cfg, optim=replace(cfg.optim, epochs=args.epochs))
    return cfg


def same_run(a: dict, b: dict) -> bool:
    """Two configs describe the same run up to the planned number of epochs and the thread count."""

    def strip(d: dict) -> dict:
        return {**d, "threads": None, "optim": {**d["optim"], "epochs": None}}

    return strip(a) == strip(b)


def retarget_schedule(sched: torch.optim.lr_scheduler.LRScheduler, cfg: TrainConfig) -> None:
    """After changing the planned epochs on resume: the cosine schedule ends at the new last epoch.

    The learning rate is set to the closed-form cosine value at the current epoch: torch's scheduler
    steps recursively from the current rate, so changing ``T_max`` alone would leave a finished
    schedule at its minimum for all the added epochs.
    """
    if isinstance(sched, torch.optim.lr_scheduler.CosineAnnealingLR):
        sched.T_max = cfg.optim.epochs
        e = min(sched.last_epoch, sched.T_max)
        lrs = [
            sched.eta_min + (base - sched.eta_min) * (1 + math.cos(math.pi * e / sched.T_max)) / 2
            for base in sched.base_lrs
        ]
        for group, lr in zip(sched.optimizer.param_groups, lrs, strict=True):
            group["lr"] = lr
        sched._last_lr = lrs


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="pranet-train", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--preset", choices=sorted(PRESETS), default="cpu")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override, e.g. optim.lr=0.01 (JSON values)")
    p.add_argument("--epochs", type=int, help="shortcut for --set optim.epochs=N")
    p.add_argument("--print-config", action="store_true", help="print the resolved config as JSON and exit")
    p.add_argument("--out", type=Path, help="run directory (default runs/<preset>)")
    p.add_argument("--resume", action="store_true", help="continue from <out>/last.pt")
    p.add_argument("--limit", type=int, help="use only this many training shapes and validation samples (smoke runs)")
    p.add_argument("--data-dir", help="data root (default $PRANET_DATA_DIR or ../shared/data)")
    p.add_argument("--workers", type=int, default=1, help="data-loader worker processes")
    p.add_argument(
        "--threads", type=int, help="torch intra-op threads (overrides the config's; not part of the run identity)"
    )
    p.add_argument("--stop-after", type=int, help="train at most this many epochs in this invocation (resume later)")
    p.add_argument("--no-progress", action="store_true")
    return p.parse_args(argv)


def setup_distributed() -> tuple[int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1:
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
        return dist.get_rank(), world
    return 0, 1


def validation_set(shapes: np.ndarray, cfg: TrainConfig, table: ActionTable) -> list[tuple[torch.Tensor, ...]]:
    """Fixed validation states from the full (post-curriculum) distribution."""
    states = StateDistribution(cfg.sampling.full, cfg.sampling.rotation, cfg.sampling.orientation_max_deg)
    ds = StateDataset(shapes, cfg, table, states, (cfg.seed, 10**6))
    return [ds[i] for i in range(len(ds))]


def evaluate_loss(net: torch.nn.Module, batches: list[tuple[torch.Tensor, ...]], cfg: TrainConfig) -> float:
    """The training loss on the fixed validation states (sample-weighted mean over batches)."""
    net.eval()
    total, count = 0.0, 0
    with torch.no_grad():
        for i in range(0, len(batches), cfg.optim.batch_size):
            batch = tuple(torch.stack(x) for x in zip(*batches[i : i + cfg.optim.batch_size], strict=True))
            loss, _ = batch_loss(net, batch, cfg)
            total += float(loss) * len(batch[0])
            count += len(batch[0])
    net.train()
    return total / max(count, 1)


@dataclass
class Run:
    """What one training run holds between epochs (rank 0 writes the files)."""

    cfg: TrainConfig
    out: Path
    rank: int
    world: int
    table: ActionTable
    net: RewardNet
    model: torch.nn.Module  # the net, or its DDP wrapper
    opt: torch.optim.Optimizer
    sched: torch.optim.lr_scheduler.LRScheduler
    data_hash: str
    start_epoch: int = 0
    best: float = float("inf")
    wall: float = 0.0


def load_shapes(args: argparse.Namespace, cfg: TrainConfig) -> tuple[np.ndarray, np.ndarray, Splits, str]:
    """``(train shapes, validation shapes, the split, the data fingerprint)`` of the seen categories."""
    data = load_modelnet40(data_dir(args.data_dir), "train")
    splits = split_train_val(data.labels, cfg.split_seed, cfg.val_fraction)
    train_shapes = data.points[splits.train]
    val_shapes = data.points[splits.val][: cfg.val_samples]
    if args.limit:
        train_shapes, val_shapes = train_shapes[: args.limit], val_shapes[: args.limit]
    return train_shapes, val_shapes, splits, splits.fingerprint(data.files)


def start_run(args: argparse.Namespace, cfg: TrainConfig, out: Path, rank: int, world: int, data_hash: str) -> Run:
    """The network (warm-started when the config says), the optimiser and schedule; resumed from ``last.pt``."""
    table = build_action_table(cfg.scales)
    net = RewardNet(cfg.net, table)
    if cfg.init and not args.resume:
        warm_start(net, Path(cfg.init), rank)
    model: torch.nn.Module = torch.nn.parallel.DistributedDataParallel(net) if world > 1 else net
    opt, sched = build_optimizer(net, cfg)
    run = Run(cfg, out, rank, world, table, net, model, opt, sched, data_hash)
    if args.resume and (out / "last.pt").exists():
        resume(run)
    elif (out / "last.pt").exists() and rank == 0:
        print(f"note: {out}/last.pt exists; starting afresh (use --resume to continue)")
    return run


def resume(run: Run) -> None:
    cfg, out = run.cfg, run.out
    ck = torch.load(out / "last.pt", map_location="cpu", weights_only=False)
    if not same_run(ck["config"], cfg.to_dict()):
        sys.exit(f"--resume: {out}/last.pt was trained with a different config; use another --out")
    run.net.load_state_dict(ck["model"])
    run.opt.load_state_dict(ck["optimizer"])
    run.sched.load_state_dict(ck["scheduler"])
    if ck["config"]["optim"]["epochs"] != cfg.optim.epochs:
        retarget_schedule(run.sched, cfg)
        print(f"resume: schedule re-targeted from {ck['config']['optim']['epochs']} to {cfg.optim.epochs} epochs")
    run.start_epoch, run.best, run.wall = ck["epoch"] + 1, ck["best_val"], ck["wall_s"]
    if run.rank == 0:
        print(f"resumed from epoch {ck['epoch']} (val {ck['val_loss']:.5f}, {run.wall / 60:.1f} min so far)")


def write_run_files(run: Run, splits: Splits) -> None:
    """``config.json`` and ``split.json`` (rank 0), and the header of ``log.csv`` for a new run."""
    (run.out / "config.json").write_text(run.cfg.to_json())
    split = {"seed": splits.seed, "train": splits.train.tolist(), "val": splits.val.tolist()}
    (run.out / "split.json").write_text(json.dumps({**split, "data_sha256": run.data_hash}))
    log_path = run.out / "log.csv"
    if not log_path.exists():
        log_path.write_text("epoch,train_loss,val_loss,lr,samples,epoch_s,wall_s\n")


def train_epoch(run: Run, epoch: int, train_shapes: np.ndarray, args: argparse.Namespace) -> tuple[float, int, float]:
    """One epoch of fresh random states (this rank's share of the shapes) -> ``(mean loss, samples, lr)``."""
    cfg, s = run.cfg, run.cfg.sampling
    comps = curriculum_states(epoch, cfg.optim.epochs, s.curriculum, s.full, s.small, s.curriculum_fraction)
    states = StateDistribution(comps, s.rotation, s.orientation_max_deg)
    order = np.random.default_rng([cfg.seed, epoch]).permutation(len(train_shapes))
    mine = order[run.rank :: run.world]
    ds = StateDataset(train_shapes[mine], cfg, run.table, states, (cfg.seed, epoch, run.rank))
    loader = DataLoader(ds, batch_size=cfg.optim.batch_size, shuffle=False, num_workers=args.workers, drop_last=True)
    it: Any = loader
    if run.rank == 0 and not args.no_progress:
        from tqdm import tqdm

        it = tqdm(loader, desc=f"epoch {epoch + 1}/{cfg.optim.epochs}", leave=False, file=sys.stdout)
    if s.visited and s.reward != "se3":
        raise ValueError("visited states are labelled by the se3 rewards; set sampling.reward to se3")
    visits = np.random.default_rng([cfg.seed, epoch, run.rank, 1])
    running, n = 0.0, 0
    for batch in it:
        steps = visit_steps(visits, s.visited, s.visited_steps)
        if steps:
            batch = visit(run.net, batch, run.table, steps)
        loss, _ = batch_loss(run.model, batch, cfg)
        size = len(batch[0])
        run.opt.zero_grad(set_to_none=True)
        loss.backward()
        if cfg.optim.grad_clip:
            torch.nn.utils.clip_grad_norm_(run.net.parameters(), cfg.optim.grad_clip)
        run.opt.step()
        running += float(loss.detach()) * size
        n += size
        if hasattr(it, "set_postfix"):
            it.set_postfix(loss=f"{running / n:.4f}")
    lr = run.opt.param_groups[0]["lr"]
    run.sched.step()
    return running / max(n, 1), n, lr


def save_epoch(run: Run, epoch: int, val_loss: float, train_loss: float, n: int, lr: float, epoch_s: float) -> None:
    """``last.pt`` (atomically), ``best.pt`` when the validation loss is the best so far, ``log.csv``."""
    run.wall += epoch_s
    run.best = min(run.best, val_loss)
    ck = {
        "epoch": epoch,
        "model": run.net.state_dict(),
        "optimizer": run.opt.state_dict(),
        "scheduler": run.sched.state_dict(),
        "config": run.cfg.to_dict(),
        "val_loss": val_loss,
        "best_val": run.best,
        "wall_s": run.wall,
        "samples": n * run.world,
        "data_sha256": run.data_hash,
        "action_fingerprint": run.table.fingerprint,
    }
    torch.save(ck, run.out / "last.pt.tmp")
    os.replace(run.out / "last.pt.tmp", run.out / "last.pt")
    if val_loss <= run.best:
        torch.save(ck, run.out / "best.pt")
    row = [
        epoch,
        f"{train_loss:.6f}",
        f"{val_loss:.6f}",
        f"{lr:.6g}",
        n * run.world,
        f"{epoch_s:.1f}",
        f"{run.wall:.1f}",
    ]
    with open(run.out / "log.csv", "a", newline="") as f:
        csv.writer(f).writerow(row)


def write_summary(run: Run) -> None:
    summary = {
        "preset": run.cfg.preset,
        "epochs": run.cfg.optim.epochs,
        "wall_s": run.wall,
        "best_val_loss": run.best,
        "data_sha256": run.data_hash,
        "action_fingerprint": run.table.fingerprint,
        "world_size": run.world,
    }
    (run.out / "summary.json").write_text(json.dumps(summary, indent=2))


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    cfg = resolve_config(args)
    if args.print_config:
        print(cfg.to_json())
        return 0
    # 1. Processes, threads, output folder, seeds.
    rank, world = setup_distributed()
    threads = args.threads or cfg.threads
    if threads:
        torch.set_num_threads(max(1, threads // world))
    out = args.out or Path("runs") / cfg.preset
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    # 2. Data, network, optimiser; resume.
    train_shapes, val_shapes, splits, data_hash = load_shapes(args, cfg)
    run = start_run(args, cfg, out, rank, world, data_hash)
    writer = None
    if rank == 0:
        write_run_files(run, splits)
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(out / "tb"))
    val = validation_set(val_shapes, cfg, run.table) if rank == 0 else []
    # 3. The epochs: train, validate, save, log.
    end_epoch = (
        cfg.optim.epochs if args.stop_after is None else min(cfg.optim.epochs, run.start_epoch + args.stop_after)
    )
    for epoch in range(run.start_epoch, end_epoch):
        t0 = time.time()
        train_loss, n, lr = train_epoch(run, epoch, train_shapes, args)
        if rank != 0:
            continue
        val_loss = evaluate_loss(run.net, val, cfg)
        epoch_s = time.time() - t0
        save_epoch(run, epoch, val_loss, train_loss, n, lr, epoch_s)
        if writer is not None:
            for tag, value in (("loss/train", train_loss), ("loss/val", val_loss), ("lr", lr)):
                writer.add_scalar(tag, value, epoch)
            writer.flush()
        print(
            f"epoch {epoch + 1}/{cfg.optim.epochs} train {train_loss:.5f} val {val_loss:.5f} "
            f"lr {lr:.3g} {epoch_s:.0f}s",
            flush=True,
        )
    # 4. The summary, once the planned epochs are done.
    if rank == 0 and end_epoch == cfg.optim.epochs:
        write_summary(run)
    if world > 1:
        # Rank 0 validates and writes while the others skip ahead to here; tearing down before it has
        # finished closed its peers' connections under them (CI, once: one rank aborted with SIGABRT).
        dist.barrier()
        dist.destroy_process_group()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
