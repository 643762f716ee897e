import csv
import json
import os
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("torch")

from pranet.training.train import main  # noqa: E402


def test_print_config_shows_the_papers_numbers(capsys):
    assert main(["--preset", "paper", "--print-config"]) == 0
    cfg = json.loads(capsys.readouterr().out)
    assert cfg["net"]["edge_widths"] == [64, 64, 128, 256, 1024] and cfg["net"]["k"] == 20
    assert cfg["net"]["heads"] == 4 and cfg["net"]["emb_dim"] == 1024
    o = cfg["optim"]
    assert (o["optimizer"], o["lr"], o["milestones"], o["epochs"], o["weight_decay"]) == (
        "sgd",
        0.1,
        [300, 700, 1000],
        1300,
        1e-4,
    )
    assert cfg["seed"] == 1234 and cfg["sampling"]["rotation"] == "isotropic"
    assert cfg["sampling"]["small"] == [10.0, 0.5 / 7]


def test_smoke_run_and_resume(tmp_path, data_root):
    def args(out, *extra):
        return [
            "--preset",
            "cpu",
            "--limit",
            "16",
            "--set",
            "optim.batch_size=8",
            "--epochs",
            "2",
            "--out",
            str(out),
            "--data-dir",
            str(data_root),
            "--no-progress",
            "--workers",
            "0",
            *extra,
        ]

    straight, split = tmp_path / "straight", tmp_path / "split"
    assert main(args(straight)) == 0
    rows = list(csv.DictReader(open(straight / "log.csv")))
    assert [r["epoch"] for r in rows] == ["0", "1"] and all(float(r["val_loss"]) > 0 for r in rows)
    assert all(None not in r for r in rows)  # every row has the header's columns, no more
    summary = json.loads((straight / "summary.json").read_text())
    assert summary["epochs"] == 2 and len(summary["data_sha256"]) == 64
    # Interrupted after one epoch, then resumed: the same result as the straight run.
    assert main(args(split, "--stop-after", "1")) == 0
    assert not (split / "summary.json").exists()
    with pytest.raises(SystemExit, match="different config"):
        main(args(split, "--resume", "--set", "optim.lr=0.5"))
    assert main(args(split, "--resume")) == 0
    resumed = list(csv.DictReader(open(split / "log.csv")))
    assert [r["epoch"] for r in resumed] == ["0", "1"]
    assert float(resumed[1]["val_loss"]) == pytest.approx(float(rows[1]["val_loss"]), rel=1e-5)


@pytest.mark.slow
def test_ddp_two_processes(tmp_path, data_root):
    out = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc_per_node=2",
        "--master_port=29533",
        "-m",
        "pranet.training.train",
        "--preset",
        "cpu",
        "--limit",
        "16",
        "--epochs",
        "1",
        "--set",
        "optim.batch_size=4",
        "--out",
        str(out),
        "--data-dir",
        str(data_root),
        "--no-progress",
        "--workers",
        "0",
    ]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["world_size"] == 2
    rows = list(csv.DictReader(open(out / "log.csv")))
    assert len(rows) == 1 and int(rows[0]["samples"]) == 16  # 2 ranks x 2 batches x 4


def test_resume_may_change_planned_epochs_and_threads_only():
    from pranet.training.config import PRESETS, parse_override
    from pranet.training.train import same_run

    cfg = PRESETS["cpu"]
    assert same_run(cfg.to_dict(), parse_override(parse_override(cfg, "optim.epochs=7"), "threads=1").to_dict())
    assert not same_run(cfg.to_dict(), parse_override(cfg, "optim.lr=0.5").to_dict())
    assert not same_run(cfg.to_dict(), parse_override(cfg, "net.k=8").to_dict())


def test_retargeted_cosine_continues_from_the_closed_form_rate():
    """A finished 4-epoch cosine resumed for 8 in all restarts from the 8-epoch curve at epoch 4, then follows it."""
    import math

    import torch

    from pranet.training.config import PRESETS, parse_override
    from pranet.training.train import build_optimizer, retarget_schedule

    cfg4 = parse_override(PRESETS["cpu"], "optim.epochs=4")
    cfg8 = parse_override(PRESETS["cpu"], "optim.epochs=8")
    net = torch.nn.Linear(2, 2)
    opt, sched = build_optimizer(net, cfg4)
    for _ in range(4):
        opt.step()
        sched.step()
    lr, lo = cfg8.optim.lr, cfg8.optim.lr * 0.01
    assert opt.param_groups[0]["lr"] == pytest.approx(lo, rel=1e-6)  # the 4-epoch schedule is spent
    retarget_schedule(sched, cfg8)
    for epoch in range(4, 8):
        expected = lo + (lr - lo) * (1 + math.cos(math.pi * epoch / 8)) / 2
        assert opt.param_groups[0]["lr"] == pytest.approx(expected, rel=1e-6)
        opt.step()
        sched.step()


def test_pose_error_is_the_mean_point_distance_of_the_two_placements():
    """RPMNet's loss: 0 for the true pose; a pure translation error of d gives d; a rotation error of θ about z
    moves a point at radius r by 2 r sin(θ/2)."""
    import torch
    from scipy.spatial.transform import Rotation

    from pranet.training.train import pose_error

    rng = np.random.default_rng(0)
    pts = torch.from_numpy(rng.normal(size=(2, 50, 3))).float()
    R = torch.from_numpy(Rotation.random(2, random_state=1).as_matrix()).float()
    t = torch.from_numpy(rng.normal(size=(2, 3))).float()
    torch.testing.assert_close(pose_error(R, t, R, t, pts), torch.zeros(2), atol=1e-6, rtol=0)
    shift = torch.tensor([[0.03, 0.0, -0.04], [0.0, 0.0, 0.0]])
    torch.testing.assert_close(pose_error(R, t + shift, R, t, pts), torch.tensor([0.05, 0.0]), atol=1e-6, rtol=0)
    ring = torch.zeros(1, 8, 3)
    angles = torch.linspace(0, 2 * np.pi, 9)[:-1]
    ring[0, :, 0], ring[0, :, 1] = 2.0 * torch.cos(angles), 2.0 * torch.sin(angles)
    Rz = torch.from_numpy(Rotation.from_euler("z", 30, degrees=True).as_matrix()).float()[None]
    expected = 2 * 2.0 * np.sin(np.deg2rad(15.0))
    got = pose_error(Rz, torch.zeros(1, 3), torch.eye(3)[None], torch.zeros(1, 3), ring)
    torch.testing.assert_close(got, torch.tensor([expected], dtype=torch.float32), atol=1e-5, rtol=0)


def test_the_state_labels_move_the_resampled_source_onto_its_truth(data_root):
    """A training sample's (R_err, t') place its resampled source points where the true pose puts them. Clean
    setting: both clouds are 256 of the same 1024 points, so about a quarter of the placed source points land on
    a target point exactly (to float32 rounding); a label off by any motion would leave none there."""
    from pranet.core.actions import build_action_table
    from pranet.training.config import PRESETS
    from pranet.training.samples import StateDistribution
    from pranet.training.train import StateDataset

    cfg = PRESETS["agent"]
    cfg = cfg.__class__.from_dict(
        {**cfg.to_dict(), "sampling": {**cfg.to_dict()["sampling"], "settings": [["clean", 1.0]]}}
    )
    from pranet.training.data import load_modelnet40

    shapes = load_modelnet40(data_root, "train").points[:4]
    ds = StateDataset(shapes, cfg, build_action_table(cfg.scales), StateDistribution(((40.0, 0.3, 1.0),)), (5,))
    for i in range(4):
        src, _, tgt, _, _, R, t = (x.numpy().astype(np.float64) for x in ds[i])
        c = src.mean(axis=0)
        placed = (src - c) @ R.T + c + t
        d = np.linalg.norm(placed[:, None] - tgt[None], axis=-1).min(axis=1)
        assert (d < 1e-5).mean() > 0.1, (d < 1e-5).mean()


def test_near_settings_apply_to_the_near_components_only():
    """With ``near_settings`` a state's component is drawn first: near ones (at most ``near_max_deg``) take their
    setting from ``near_settings``, far ones from ``settings``, and the state is drawn from that component."""
    from scipy.spatial.transform import Rotation

    from pranet.core.actions import build_action_table
    from pranet.training.config import PRESETS
    from pranet.training.samples import StateDistribution
    from pranet.training.train import StateDataset

    cfg = PRESETS["agent"]
    sampling = {**cfg.to_dict()["sampling"], "settings": [["clean", 1.0]], "near_settings": [["partial", 1.0]]}
    cfg = cfg.__class__.from_dict({**cfg.to_dict(), "sampling": {**sampling, "near_max_deg": 10.0}})
    shapes = np.random.default_rng(0).normal(size=(24, 1024, 3))
    states = StateDistribution(((60.0, 0.5, 1.0), (10.0, 0.1, 1.0)))
    ds = StateDataset(shapes, cfg, build_action_table(cfg.scales), states, (5,))
    drawn = [ds.setting_and_component(np.random.default_rng([5, i])) for i in range(len(shapes))]
    assert {c for _, c in drawn} == {0, 1}
    assert all((s == "partial") == (c == 1) for s, c in drawn), drawn
    angles = [np.rad2deg(Rotation.from_matrix(ds[i][5].numpy().astype(np.float64)).magnitude()) for i in range(24)]
    assert all(a <= 10.0 + 1e-4 for a, (_, c) in zip(angles, drawn, strict=True) if c == 1), angles
    assert any(a > 10.0 for a, (_, c) in zip(angles, drawn, strict=True) if c == 0), angles
    plain = StateDataset(shapes, PRESETS["agent"], build_action_table(cfg.scales), states, (5,))
    assert plain.setting_and_component(np.random.default_rng(1))[1] is None


def test_overlap_labels_mark_the_shared_part_at_the_true_pose():
    """Target = the half x > 0 of a plane sampled at random, the source the whole plane moved off by a known pose:
    at the true pose the source's x > 0 part overlaps, its x < 0 part does not, and every target point does."""
    import torch
    from scipy.spatial.transform import Rotation

    from pranet.training.train import overlap_labels

    rng = np.random.default_rng(0)
    plane = rng.uniform(-1.0, 1.0, (256, 3)) * [1.0, 1.0, 0.0]
    target = plane[plane[:, 0] > 0]
    R = Rotation.from_rotvec([0.2, -0.1, 0.3]).as_matrix()
    m = plane.mean(axis=0)
    source = (plane - m) @ R + m + [0.4, -0.3, 0.2]  # rows Rᵀ (p - m) + c, c = m + (0.4, -0.3, 0.2) its centroid
    t = m - source.mean(axis=0)  # R (source - c) + c + t = plane
    src_labels, tgt_labels = overlap_labels(
        *(torch.tensor(a[None], dtype=torch.float32) for a in (source, target)),
        torch.tensor(R[None], dtype=torch.float32),
        torch.tensor(t[None], dtype=torch.float32),
    )
    x = plane[:, 0]
    assert src_labels[0][x > 0.2].min() == 1 and src_labels[0][x < -0.2].max() == 0
    assert tgt_labels.min() == 1
