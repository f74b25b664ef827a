"""Checkpoints of a training run: everything needed to continue it exactly.

Saved at episode boundaries (after an episode's training; every car has just been reset for
its next episode, by either collector), for every member of the population at once: the loss
module (stacked networks and, for SPG, the temperatures), both optimisers, the replay memory
(storage and write cursor), the members' torch generators and the global ones, the
simulator's state (cars, tracks, random streams), the episode counter, each member's learning
curve and status (frozen members stay frozen), the run's settings and the code version.

Written atomically (``door.files.write_atomic``: a temporary file, fsync, rename), so a crash
mid-write leaves the previous checkpoint in place and a full disk is reported as such. The file
is sealed: one line, ``racing-rl checkpoint sha256 <digest>``, then torch's zip, the digest that
of the zip's bytes, so that a flipped bit anywhere (torch does not check its zip's CRCs) is
refused before anything is loaded (checkpoints from before the seal: their zip's CRCs are
checked instead). Each member's state records the size and SHA-256 of its ``metrics.csv`` at that
moment, which a resume checks before it keeps those rows. Loaded with
``torch.load(weights_only=True)``: only tensors and plain containers, no code; a file holding
anything else is refused as possibly hostile, never loaded another way.
"""

from __future__ import annotations

import hashlib
import io
import pickle
import random
import zipfile
from pathlib import Path

import numpy as np
import torch

from door import files
from engine.outputs import first_line, write_atomic
from engine.rundir import checkpoints as in_folder  # noqa: F401 (part of this module's interface)

CHECKPOINT_FILE = "checkpoint.pt"  # a population's; each part of a split one has checkpoint-<first seed>.pt
VERSION = 3  # 2: the simulator's whole state; 3: populations (every member, their generators)
SEAL = b"racing-rl checkpoint sha256 "  # then 64 hexadecimal digits and a newline, then torch's zip


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
    """Atomically replace ``path`` with ``payload``, sealed with its SHA-256."""
    buffer = io.BytesIO()
    torch.save({"version": VERSION, **payload}, buffer)
    body = buffer.getbuffer()  # no copy of what may be a large replay memory
    write_atomic(Path(path), [SEAL + hashlib.sha256(body).hexdigest().encode() + b"\n", body])


def save_tensors(path: Path, obj) -> None:
    """``torch.save`` ``obj`` to ``path`` atomically (weights: plain torch files, for any reader)."""
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    write_atomic(Path(path), buffer.getvalue())


def unsealed(path: Path, data: bytes) -> bytes:
    """The torch zip inside a sealed checkpoint, its digest checked; an older checkpoint's zip, its
    CRCs checked. ``ValueError`` saying what differs."""
    if data.startswith(SEAL):
        head, _, body = data.partition(b"\n")
        if hashlib.sha256(body).hexdigest().encode() != head[len(SEAL):]:
            raise ValueError(f"{path} differs from the file that was written (its content no longer matches the "
                             "SHA-256 sealed in it): damaged")
        return body
    if not data.startswith(b"PK\x03\x04"):  # neither sealed nor an older checkpoint's bare zip
        raise ValueError(f"{path} is not a readable checkpoint (it starts with neither a checkpoint's seal line nor a "
                         "torch zip: damaged, or another file)")
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            bad = archive.testzip()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, RuntimeError, zipfile.LargeZipFile) as err:
        raise ValueError(f"{path} is not a readable checkpoint ({first_line(err)})") from None
    if bad is not None:
        raise ValueError(f"{path} differs from the file that was written (the CRC of its part {bad} does not match): "
                         "damaged")
    return data


def load_tensors(path: Path, what: str = "file", sealed: bool = False, limit: int | None = None):
    """``torch.load(path, weights_only=True)``; ``ValueError`` with one clear sentence if the file is
    empty, truncated, not torch's, holds more than tensors and plain containers, or is larger than
    ``limit`` bytes (refused unread: weights pass ``engine.limits.weights_limit``, what their shapes may need;
    a checkpoint, None, is bounded by half the memory available). ``sealed``: a checkpoint, whose seal
    (``unsealed``) is checked first."""
    path = Path(path)
    try:
        if sealed:  # its first bytes first: a file that is no checkpoint is refused before it is read whole
            with files.stream(path) as f:
                head = f.read(len(SEAL) + 65)
            if head and not head.startswith((SEAL, b"PK\x03\x04")):
                raise ValueError(f"{path} is not a readable checkpoint (it starts with neither a checkpoint's seal "
                                 "line nor a torch zip: damaged, or another file)")
        data = files.read(path, _load_limit() if limit is None else min(limit, _load_limit()), what)
    except files.FileRefused as err:
        raise ValueError(str(err)) from None
    except OSError as err:
        raise ValueError(f"{path} is not a readable {what} ({first_line(err)})") from None
    if len(data) == 0:
        raise ValueError(f"{path} is empty (0 bytes)")
    if sealed:
        data = unsealed(path, data)
    return load_tensors_from(io.BytesIO(data), path, what)


def load_tensors_from(source: io.BytesIO, path, what: str = "file"):
    """``torch.load(source, weights_only=True)`` of bytes already read (``path`` names them in
    messages); the one place tensors are unpacked: ``ValueError`` with one clear sentence if they
    are not torch's or hold more than tensors and plain containers."""
    try:
        return torch.load(source, weights_only=True, map_location="cpu")
    except pickle.UnpicklingError as err:
        reason = _unpickler_reason(str(err))
        if reason.startswith("Unsupported global"):
            raise ValueError(f"{path} holds objects other than tensors and plain containers "
                             f"({reason.split(' was not')[0].split(' whose module')[0][:120]}); it "
                             f"was refused unread, as loading them could run code (not {'an' if what[:1] in 'aeiou' else 'a'} {what} written here)") from None
        raise ValueError(f"{path} is not a readable {what} (UnpicklingError: {reason[:200]})") from None
    except (RuntimeError, EOFError, OSError, zipfile.BadZipFile, TypeError, AttributeError, KeyError) as err:
        raise ValueError(f"{path} is not a readable {what} ({first_line(err)})") from None


def _load_limit() -> int:
    """The largest file a load may read: half the memory available (it is read, then unpacked; 64 GiB
    where the memory available is unknown)."""
    from engine.limits import available_bytes

    available = available_bytes()
    return 1 << 36 if available is None else max(available // 2, 1 << 20)


def _unpickler_reason(message: str) -> str:
    """The reason inside torch's weights-only refusal, without its advice to load the file another way
    (which is exactly what must not be done with a file that may be hostile)."""
    tail = message.split("WeightsUnpickler error:", 1)[-1]
    advice = ("Weights only load failed", "In PyTorch", "Re-running", "Check the documentation", "will likely succeed")
    lines = [line.strip() for line in tail.splitlines() if line.strip() and not line.strip().startswith(advice)]
    for line in lines:
        if "GLOBAL" in line or "Unsupported" in line or "blocked" in line:
            return "Unsupported global: " + line.removeprefix("Unsupported global: ")
    return lines[0] if lines else "not a file of tensors"


def load(path: Path) -> dict:
    """The checkpoint at ``path``; ``CheckpointError`` saying what is wrong if it is unusable."""
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"no checkpoint at {path}")
    try:
        payload = load_tensors(path, "checkpoint", sealed=True)
    except ValueError as err:
        raise CheckpointError(f"{err}; move it away (or pass overwrite=true) to start the run afresh") from None
    if not isinstance(payload, dict) or payload.get("version") != VERSION:
        raise CheckpointError(f"{path} is not a version-{VERSION} checkpoint of train.py; "
                              "move it away (or pass overwrite=true) to start the run afresh")
    return payload
