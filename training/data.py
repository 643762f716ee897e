"""ModelNet40 loading and the train/val/test splits (paper, "Experiments"; RPMNet's unseen-category protocol).

Reads either this project's ``modelnet40/{train,test}.h5`` (1024 points, float16) or the original
``modelnet40_ply_hdf5_2048/ply_data_{train,test}*.h5`` files (2048 points). The data root comes from
``PRANET_DATA_DIR`` (default ``../shared/data``), read at the edge by the CLIs and passed in.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pranet.engine.runtime import sha256_file

DATA_ENV = "PRANET_DATA_DIR"
DEFAULT_DATA_DIR = "../shared/data"
SEEN_CATEGORIES = range(0, 20)
UNSEEN_CATEGORIES = range(20, 40)


def data_dir(explicit: str | os.PathLike | None = None) -> Path:
    """The data root: ``explicit``, else ``$PRANET_DATA_DIR``, else ``../shared/data``."""
    return Path(explicit or os.environ.get(DATA_ENV) or DEFAULT_DATA_DIR)


def modelnet_dir(root: Path) -> Path:
    """The folder holding ModelNet40 under ``root`` (ours or the original release), or raise."""
    for candidate in (root / "modelnet40", root / "modelnet40_ply_hdf5_2048", root):
        if (candidate / "train.h5").exists() or list(candidate.glob("ply_data_train*.h5")):
            return candidate
    raise FileNotFoundError(
        f"no ModelNet40 under {root}: expected modelnet40/train.h5 or modelnet40_ply_hdf5_2048/ply_data_train*.h5 "
        f"(set {DATA_ENV})"
    )


@dataclass(frozen=True)
class ModelNet40:
    points: np.ndarray  # (S, P, 3) float32, P = 1024 (ours) or 2048 (original)
    labels: np.ndarray  # (S,) int64
    files: tuple[Path, ...]


def load_modelnet40(root: Path, split: str) -> ModelNet40:
    """``split``: ``"train"`` or ``"test"``."""
    import h5py

    folder = modelnet_dir(root)
    ours = folder / f"{split}.h5"
    files = [ours] if ours.exists() else sorted(folder.glob(f"ply_data_{split}*.h5"), key=lambda p: int(p.stem[-1]))
    if not files:
        raise FileNotFoundError(f"no {split} split in {folder}")
    pts, labels = [], []
    for f in files:
        with h5py.File(f, "r") as h:
            pts.append(h["data"][:].astype(np.float32))
            labels.append(h["label"][:].reshape(-1).astype(np.int64))
    return ModelNet40(np.concatenate(pts), np.concatenate(labels), tuple(files))


@dataclass(frozen=True)
class Splits:
    train: np.ndarray  # indices into the train file, categories 0-19
    val: np.ndarray
    seed: int

    def fingerprint(self, files: tuple[Path, ...]) -> str:
        """sha256 over the data files and the chosen indices: the 'data hash' of a model card."""
        h = hashlib.sha256()
        for f in files:
            h.update(sha256_file(f).encode())
        h.update(json.dumps({"train": self.train.tolist(), "val": self.val.tolist()}).encode())
        return h.hexdigest()


def split_train_val(labels: np.ndarray, seed: int, val_fraction: float = 0.1) -> Splits:
    """Seeded ~90/10 split of the shapes of categories 0-19 (5112 -> 4601 / 511 with our default)."""
    seen = np.flatnonzero(np.isin(labels, list(SEEN_CATEGORIES)))
    perm = np.random.default_rng(seed).permutation(seen)
    n_val = int(round(val_fraction * len(seen)))
    return Splits(train=np.sort(perm[n_val:]), val=np.sort(perm[:n_val]), seed=seed)


def test_indices(labels: np.ndarray) -> np.ndarray:
    """The unseen-category test shapes: categories 20-39 of the test split (1266)."""
    return np.flatnonzero(np.isin(labels, list(UNSEEN_CATEGORIES)))
