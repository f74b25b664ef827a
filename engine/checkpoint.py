"""Checkpoints of a training run: everything needed to continue it exactly.

Saved at episode boundaries (after an episode's training; every car has just been reset for
its next episode, by either collector), for every member of the population at once: the loss
module (stacked networks and, for SPG, the temperatures), both optimisers, the replay memory
(storage and write cursor), the members' torch generators and the global ones, the
simulator's state (cars, tracks, random streams), the episode counter, each member's learning
curve and status (frozen members stay frozen), the run's settings and the code version.

Written atomically (a temporary file, fsync, rename), so a crash mid-write leaves the previous
checkpoint in place. Loaded with ``torch.load(weights_only=True)``: only tensors and plain
containers, no code.
"""

from __future__ import annotations

import os
import random
from pathlib import Path

import numpy as np
import torch

CHECKPOINT_FILE = "checkpoint.pt"  # a population's; each part of a split one has checkpoint-<first seed>.pt
VERSION = 3  # 2: the simulator's whole state; 3: populations (every member, their generators)


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used (corrupt, another version or another run's)."""


def capture_rng() -> dict:
    kind, keys, pos, has_gauss, gauss = np.random.get_state()
    return {"torch": torch.get_rng_state(), "numpy": [torch.from_numpy(keys.astype(np.int64)), pos, has_gauss, gauss],
            "python": random.getstate()}


def restore_rng(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    keys, pos, has_gauss, gauss = state["numpy"]
    np.random.set_state(("MT19937", keys.numpy().astype(np.uint32), int(pos), int(has_gauss), float(gauss)))
    version, internal, gauss_next = state["python"]
    random.setstate((version, tuple(internal), gauss_next))


def arrays_to_tensors(state: dict) -> dict:
    """NumPy arrays (e.g. the simulator's state) as int64 / float64 tensors, for ``weights_only``."""
    return {key: torch.from_numpy(np.asarray(value).astype(np.int64 if value.dtype.kind in "uib" else np.float64))
            for key, value in state.items()}


def arrays_from_tensors(state: dict) -> dict:
    return {key: value.numpy() for key, value in state.items()}


def save(path: Path, payload: dict) -> None:
    """Atomically replace ``path`` with ``payload``."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        torch.save({"version": VERSION, **payload}, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def in_folder(folder: Path) -> list[Path]:
    """The checkpoints in a run folder: ``checkpoint.pt`` and those of a split population's parts."""
    return sorted(p for p in Path(folder).glob("checkpoint*.pt") if p.is_file())


def load(path: Path) -> dict:
    """The checkpoint at ``path``; ``CheckpointError`` saying what is wrong if it is unusable."""
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"no checkpoint at {path}")
    try:
        payload = torch.load(path, weights_only=True, map_location="cpu")
    except Exception as err:  # torch raises several types for truncated or foreign files
        raise CheckpointError(f"{path} is not a readable checkpoint ({type(err).__name__}: "
                              f"{str(err).splitlines()[0][:200]}); delete it to start the run afresh") from None
    if not isinstance(payload, dict) or payload.get("version") != VERSION:
        raise CheckpointError(f"{path} is not a version-{VERSION} checkpoint of train.py; "
                              "delete it to start the run afresh")
    return payload
