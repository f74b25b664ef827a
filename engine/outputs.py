"""What a run leaves in its folder: metrics.csv, summary.json, weights, and TorchRL logs."""

from __future__ import annotations

import csv
import errno
import hashlib
import io
import json
import math
import os
import shutil
from pathlib import Path
from typing import Any

METRICS_FILE = "metrics.csv"
SUMMARY_FILE = "summary.json"
EPISODE_COLUMNS = ("episode", "total_reward", "crashes", "final_checkpoint")


FINAL_STATUSES = ("completed", "diverged", "incomplete")  # a run that ended ("incomplete": an SB3 baseline's, short)
SUMMARY_KEYS = ("algo", "er", "seed", "status", "final_mean", "episodes", "settings")


class RunFolderError(ValueError):
    """A folder that does not hold a usable trained run."""


class DiskFull(RunFolderError):
    """A file could not be written for want of space; the previous version of it (if any) is intact."""

    def __init__(self, path: Path, needed: int):
        self.path, self.needed = Path(path), needed
        free = free_bytes(self.path.parent)
        have = "" if free is None else f", {free:,} are free"
        super().__init__(f"no space left on the device of {self.path}: writing it needs {needed:,} bytes{have}; "
                         "the folder keeps its last good files (free some space and run the same command again)")


def free_bytes(folder: Path) -> int | None:
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def first_line(err: BaseException, limit: int = 200) -> str:
    """``TypeName: first line of the message`` (the type alone for an empty message)."""
    lines = [line for line in str(err).splitlines() if line.strip()]
    return f"{type(err).__name__}: {lines[0][:limit]}" if lines else type(err).__name__


def metric_columns(source) -> list[str]:
    """metrics.csv's columns: per-episode results, then the diagnostics of the updates (a loss's
    or phase runner's ``critic_metrics`` and ``actor_metrics``)."""
    return (list(EPISODE_COLUMNS)
            + [f"critic/{key}" for key in source.critic_metrics]
            + [f"actor/{key}" for key in source.actor_metrics])


class MetricsWriter:
    """metrics.csv, one row per episode, flushed as written; plus an optional TorchRL logger."""

    def __init__(self, out_dir: Path, columns: list[str], logger_kind: str = "none", keep_rows: int = 0):
        """``keep_rows``: continue after the first this-many rows of an existing metrics.csv
        (a resumed run: rows after its checkpoint are dropped and written again)."""
        self.path = out_dir / METRICS_FILE
        self.columns = columns
        kept = self._kept_rows(keep_rows)
        text = io.StringIO(newline="")
        csv.DictWriter(text, fieldnames=columns).writeheader()
        text.writelines(kept)
        write_atomic(self.path, text.getvalue().encode())  # a crash now leaves the old file whole
        self.file = open(self.path, "a", newline="")  # then rows are appended: a crash cuts the last one at most
        self.writer = csv.DictWriter(self.file, fieldnames=columns, extrasaction="raise")
        self.logger = make_torchrl_logger(logger_kind, out_dir)

    def _kept_rows(self, count: int) -> list[str]:
        if count == 0:
            return []
        try:
            with open(self.path, newline="") as f:  # keep the csv module's line endings
                lines = f.read().splitlines(keepends=True)
        except FileNotFoundError:
            lines = []
        except (OSError, UnicodeDecodeError) as err:
            raise RunFolderError(f"{self.path} cannot be read ({first_line(err)}); the run cannot continue from "
                                 "its checkpoint: pass overwrite=true to start it afresh") from None
        if len(lines) < count + 1 or lines[0].rstrip("\r\n") != ",".join(self.columns):
            found = "is missing" if not lines else f"holds {max(0, len(lines) - 1)} rows"
            raise RunFolderError(f"{self.path} {found}, but the run's checkpoint counts {count} episode rows: "
                                 "the run cannot continue exactly; pass overwrite=true to start it afresh")
        return lines[1:count + 1]

    def write(self, row: dict[str, Any]) -> None:
        line = {key: _format(row.get(key)) for key in self.columns}
        try:
            self.writer.writerow(line)
            self.file.flush()
        except OSError as err:
            if err.errno in (errno.ENOSPC, errno.EDQUOT):
                raise DiskFull(self.path, len(",".join(map(str, line.values()))) + 1) from None
            raise
        if self.logger is not None:
            step = int(row["episode"])
            for key, value in row.items():
                if key != "episode" and value is not None:
                    self.logger.log_scalar(f"train/{key}", float(value), step=step)

    def sync(self) -> None:
        """Flush the rows to the disk (before a checkpoint that counts them)."""
        self.file.flush()
        os.fsync(self.file.fileno())

    def close(self) -> None:
        try:
            self.file.close()
        except OSError:  # a full disk: the rows that reached the file are what a resume keeps
            pass


def _format(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else str(value)
    return value


def make_torchrl_logger(kind: str, out_dir: Path):
    """A ``torchrl.record.loggers`` logger writing under ``out_dir/logs`` (``None`` for "none")."""
    if kind == "none":
        return None
    if kind == "tensorboard":
        try:
            import tensorboard  # noqa: F401
        except ImportError:
            raise RuntimeError("logger=tensorboard needs the tensorboard package: "
                               "pip install -c constraints/cpu.txt -e '.[tensorboard]'") from None
    from torchrl.record.loggers import get_logger

    return get_logger(kind, logger_name=str(out_dir), experiment_name="logs")


def write_table(path: Path, rows: list[dict]) -> None:
    """Rows (dicts with the same keys) as a CSV file, its header the first row's keys; prints where."""
    path = Path(path)
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, text.getvalue().encode())
    print(f"wrote {path} ({len(rows)} rows)")


def write_atomic(path: Path, data: bytes) -> None:
    """Replace ``path`` with ``data`` so that a crash at any byte leaves the old file or the new one:
    a temporary file beside it, flushed to the disk, renamed over it. A full disk raises ``DiskFull``
    and leaves no temporary file."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    free = free_bytes(path.parent)
    if free is not None and free < len(data):
        raise DiskFull(path, len(data))
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        if err.errno in (errno.ENOSPC, errno.EDQUOT):
            raise DiskFull(path, len(data)) from None
        raise
    try:  # the rename itself reaches the disk
        fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        pass


def write_json_atomic(path: Path, data: dict) -> None:
    """Write ``data`` as JSON atomically (``write_atomic``)."""
    write_atomic(path, (json.dumps(data, indent=2, sort_keys=False) + "\n").encode())


def file_record(folder: Path, names: tuple[str, ...]) -> dict:
    """{name: {"bytes": size, "sha256": digest}} of the files a summary stands for (those present)."""
    record = {}
    for name in names:
        path = Path(folder) / name
        if path.is_file():
            data = path.read_bytes()
            record[name] = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    return record


def read_summary(out_dir: Path) -> dict | None:
    """The run's summary.json; ``None`` if there is none; ``RunFolderError`` naming what is wrong
    if the file is there but is not a summary written by train.py (unreadable, not JSON, not an
    object, keys missing). A damaged summary is never taken for a missing one."""
    path = Path(out_dir) / SUMMARY_FILE
    try:
        text = path.read_text()
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError) as err:
        raise RunFolderError(f"{path} cannot be read ({first_line(err)})") from None
    try:
        summary = json.loads(text)
    except json.JSONDecodeError as err:
        raise RunFolderError(f"{path} is not JSON ({'empty' if not text.strip() else first_line(err)})") from None
    if not isinstance(summary, dict):
        raise RunFolderError(f"{path} holds a JSON {type(summary).__name__}, not a summary (an object)")
    missing = [key for key in SUMMARY_KEYS if key not in summary]
    if missing:
        raise RunFolderError(f"{path} lacks {missing}: not a summary written by train.py")
    if not isinstance(summary["settings"], (dict, type(None))) or not isinstance(summary["status"], str):
        raise RunFolderError(f"{path} has a malformed status or settings: not a summary written by train.py")
    return summary
