"""What a run leaves in its folder: metrics.csv, summary.json, weights, and TorchRL logs."""

from __future__ import annotations

import csv
import errno
import hashlib
import io
import json
import math
import os
from pathlib import Path
from typing import Any

from door import files
from door.files import DiskFull, FileRefused, free_bytes  # noqa: F401 (part of this module's interface)

METRICS_FILE = "metrics.csv"
SUMMARY_FILE = "summary.json"
EPISODE_COLUMNS = ("episode", "total_reward", "crashes", "final_checkpoint")


SUMMARY_LIMIT = 16 * 2**20  # bytes: a summary is a few kilobytes
ROWS_LIMIT = 1 << 30  # bytes of metrics.csv read to resume (its checkpoint's record says how many, when it has one)
RECORDABLE_FILES = (METRICS_FILE, "actor.pt", "critic.pt", "model.zip")  # what a summary's "files" may name
FINAL_STATUSES = ("completed", "diverged", "incomplete")  # a run that ended ("incomplete": an SB3 baseline's, short)
SUMMARY_KEYS = ("algo", "er", "seed", "status", "final_mean", "episodes", "settings")


class RunFolderError(FileRefused):
    """A folder that does not hold a usable trained run."""


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
    """metrics.csv, one row per episode, each appended whole or not at all; plus an optional TorchRL logger."""

    def __init__(self, out_dir: Path, columns: list[str], logger_kind: str = "none", keep_rows: int = 0,
                 expect: dict | None = None):
        """``keep_rows``: continue after the first this-many rows of an existing metrics.csv
        (a resumed run: rows after its checkpoint are dropped and written again); ``expect``: the
        size and SHA-256 of those rows and the header as the checkpoint recorded them (``record``),
        checked before they are kept."""
        self.path = out_dir / METRICS_FILE
        self.columns = columns
        # the logger first: a file it cannot write is refused before metrics.csv is touched
        self.logger = make_torchrl_logger(logger_kind, out_dir, [f"train/{c}" for c in columns if c != "episode"])
        kept = kept_rows(self.path, keep_rows, expect, ",".join(columns))
        text = io.StringIO(newline="")
        csv.DictWriter(text, fieldnames=columns).writeheader()
        start = text.getvalue().encode() + kept
        write_atomic(self.path, start)  # a crash now leaves the old file whole
        # what this run wrote, as it wrote it: the summary seals these bytes, not whatever the file holds
        self.written, self.written_bytes = hashlib.sha256(start), len(start)
        # then rows are appended, each in one write; one that does not fit is cut off again
        self.fd = files.open_append(self.path)
        self.size = os.fstat(self.fd).st_size

    def record(self) -> dict:
        """Size and SHA-256 of the file as it is on the disk now (a checkpoint keeps it: ``expect``), which must
        be what this run wrote (``check_unchanged``)."""
        self.sync()
        self.check_unchanged()
        return bytes_record(files.read(self.path, ROWS_LIMIT, "metrics.csv"))

    def write(self, row: dict[str, Any]) -> None:
        line = {key: _format(row.get(key)) for key in self.columns}
        text = io.StringIO(newline="")
        csv.DictWriter(text, fieldnames=self.columns, extrasaction="raise").writerow(line)
        self.append(text.getvalue().encode())
        if self.logger is not None:
            step = int(row["episode"])
            for key, value in row.items():
                if key != "episode" and value is not None:
                    self.logger.log_scalar(f"train/{key}", float(value), step=step)

    def append(self, data: bytes) -> None:
        """Append ``data`` in one write; if it does not all reach the file, the file is cut back to
        where it was (a full disk raises ``DiskFull``)."""
        try:
            written = os.write(self.fd, data)
            if written != len(data):
                raise OSError(errno.ENOSPC, "no space left for the whole row")
        except OSError as err:
            try:
                os.ftruncate(self.fd, self.size)
            except OSError:
                pass
            if err.errno in (errno.ENOSPC, errno.EDQUOT):
                raise DiskFull(self.path, len(data)) from None
            raise
        self.size += len(data)
        self.written.update(data)
        self.written_bytes += len(data)

    def check_unchanged(self) -> None:
        """``RunFolderError`` if metrics.csv is not exactly the bytes this run wrote (a row edited, added or
        cut behind its back while it trained): a run seals what it wrote, never what the file holds at the end."""
        now = file_digest(self.path)
        if now != {"bytes": self.written_bytes, "sha256": self.written.hexdigest()}:
            raise RunFolderError(f"{self.path} changed while the run trained (it holds {now['bytes']:,} bytes; the run "
                                 f"wrote {self.written_bytes:,}): its rows are not the run's own, so the run is not "
                                 "sealed; run the same command with overwrite=true to train it afresh")

    def sync(self) -> None:
        """Flush the rows to the disk (before a checkpoint that counts them)."""
        try:
            os.fsync(self.fd)
        except OSError as err:
            if err.errno in (errno.ENOSPC, errno.EDQUOT):
                raise DiskFull(self.path, 0) from None
            raise

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
        for handle in getattr(getattr(self.logger, "experiment", None), "files", {}).values():
            handle.close()


def kept_rows(path: Path, count: int, expect: dict | None, header: str | None = None) -> bytes:
    """The first ``count`` rows of metrics.csv at ``path`` (bytes, the header left out), checked against
    what a checkpoint recorded of them (``expect``: size and SHA-256 with the header; None for
    checkpoints from before that record) and, if given, the header; ``RunFolderError`` otherwise."""
    if count == 0:
        return b""
    try:
        data = files.read(path, ROWS_LIMIT, "metrics.csv")
        if expect is not None and isinstance(expect.get("bytes"), int):
            data = data[:expect["bytes"]]  # the rows it recorded; those after it are written again
    except FileNotFoundError:
        data = b""
    except OSError as err:
        raise RunFolderError(f"{path} cannot be read ({first_line(err)}); the run cannot continue from "
                             "its checkpoint: pass overwrite=true to start it afresh") from None
    lines = data.splitlines(keepends=True)
    if len(lines) < count + 1 or (header is not None and lines[0].rstrip(b"\r\n") != header.encode()):
        found = "is missing" if not lines else f"holds {max(0, len(lines) - 1)} rows"
        raise RunFolderError(f"{path} {found}, but the run's checkpoint counts {count} episode rows: "
                             "the run cannot continue exactly; pass overwrite=true to start it afresh")
    if expect is not None and bytes_record(b"".join(lines[:count + 1])) != expect:
        raise RunFolderError(f"{path}: its first {count} row{'s' if count != 1 else ''} differ from those its "
                             "checkpoint recorded (their SHA-256): edited or damaged since; the run cannot continue "
                             "exactly: pass overwrite=true to start it afresh")
    return b"".join(lines[1:count + 1])


def bytes_record(data: bytes) -> dict:
    return {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}


file_digest = files.digest  # {"bytes", "sha256"} of a file, read in pieces (the door's)


def _format(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else str(value)
    return value


def make_torchrl_logger(kind: str, out_dir: Path, scalars: list[str] = ()):
    """A ``torchrl.record.loggers`` logger writing under ``out_dir/logs`` (``None`` for "none"). Its
    folder is checked whole first (``door.files.check_tree``); the CSV logger's file of each of
    ``scalars`` is opened through the file door and handed to it (its ``experiment.files``), so it
    writes through the door, never opening a file of its own; TensorBoard's logger writes one new
    event file of a fresh name into the checked folder."""
    if kind == "none":
        return None
    if kind == "tensorboard":
        try:
            import tensorboard  # noqa: F401
        except ImportError:
            raise RuntimeError("logger=tensorboard needs the tensorboard package: "
                               "pip install -c constraints/cpu.txt -e '.[tensorboard]'") from None
    from torchrl.record.loggers import get_logger

    # TorchRL's loggers open their own files: they write only into a logs/ folder checked whole first
    # (a real folder of the run's, nothing below it a link, a special file or a hard link)
    logs = Path(out_dir) / "logs"
    files.folder(logs, out_dir, create=True)
    files.check_tree(logs)
    opened = {}
    if kind == "csv":  # TorchRL's CSVExperiment.add_scalar opens os.path.join(log_dir, "scalars", name + ".csv")
        for name in scalars:
            path = os.path.join(str(logs), "scalars", name + ".csv")
            opened[path] = files.open_log(path, logs)
    logger = get_logger(kind, logger_name=str(out_dir), experiment_name="logs")
    if kind == "csv":
        logger.experiment.files.update(opened)
    return logger


def write_table(path: Path, rows: list[dict]) -> None:
    """Rows (dicts) as a CSV file, its header every key in the order first seen (a row without a key
    leaves its cell empty), no cell a spreadsheet runs as a formula (``engine.names.csv_cell``: a name read back
    with ``csv_name``); prints where."""
    from engine.names import csv_cell

    path = Path(path)
    rows = [{key: csv_cell(value) for key, value in row.items()} for row in rows]
    if not rows:
        print(f"no rows to write: {path} was not written")
        return
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=list(dict.fromkeys(key for row in rows for key in row)))
    writer.writeheader()
    writer.writerows(rows)
    files.folder(path.parent, path.parent, create=True)  # a folder the user names (it may be a link)
    files.write_text(path, text.getvalue())
    print(f"wrote {path} ({len(rows)} rows)")


write_atomic = files.write_atomic  # the door's (door/files.py)


def write_json_atomic(path: Path, data: dict) -> None:
    """Write ``data`` as JSON atomically (``write_atomic``)."""
    write_atomic(path, (json.dumps(data, indent=2, sort_keys=False) + "\n").encode())


DIGEST_KEY = "sha256"  # a summary's digest of its own content (``seal``)


def content_digest(summary: dict) -> str:
    """SHA-256 of a summary's content as JSON reads it back (keys sorted, its own digest left out)."""
    plain = json.loads(json.dumps({k: v for k, v in summary.items() if k != DIGEST_KEY}))
    return hashlib.sha256(json.dumps(plain, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def seal(summary: dict) -> dict:
    """``summary`` with the digest of its own content as its last key: a summary edited or damaged
    after it was written no longer matches it (``read_summary`` checks)."""
    return {**{k: v for k, v in summary.items() if k != DIGEST_KEY}, DIGEST_KEY: content_digest(summary)}


def write_summary(folder: Path, summary: dict) -> dict:
    """Write a run's sealed summary.json atomically; returns it as written."""
    sealed = seal(summary)
    write_json_atomic(Path(folder) / SUMMARY_FILE, sealed)
    return sealed


def file_record(folder: Path, names: tuple[str, ...]) -> dict:
    """{name: {"bytes": size, "sha256": digest}} of the files a summary stands for (those present)."""
    record = {}
    for name in names:
        path = Path(folder) / name
        if files.is_file(path):
            record[name] = file_digest(path)
    return record


def read_summary(out_dir: Path) -> dict | None:
    """The run's summary.json; ``None`` if there is none; ``RunFolderError`` naming what is wrong
    if the file is there but is not a summary written by train.py (unreadable, not JSON, not an
    object, keys missing). A damaged summary is never taken for a missing one."""
    path = Path(out_dir) / SUMMARY_FILE
    try:
        text = files.read_text(path, SUMMARY_LIMIT, "summary")
    except FileNotFoundError:
        return None
    except FileRefused as err:
        raise RunFolderError(str(err)) from None
    try:
        summary = json.loads(text)
    except (ValueError, RecursionError) as err:  # not JSON, nested past Python's limit, an integer of 5,000 digits
        raise RunFolderError(f"{path} is not JSON ({'empty' if not text.strip() else first_line(err)})") from None
    if not isinstance(summary, dict):
        raise RunFolderError(f"{path} holds a JSON {type(summary).__name__}, not a summary (an object)")
    missing = [key for key in SUMMARY_KEYS if key not in summary]
    if missing:
        raise RunFolderError(f"{path} lacks {missing}: not a summary written by train.py")
    if not isinstance(summary["settings"], (dict, type(None))) or not isinstance(summary["status"], str):
        raise RunFolderError(f"{path} has a malformed status or settings: not a summary written by train.py")
    if DIGEST_KEY in summary and summary[DIGEST_KEY] != content_digest(summary):
        raise RunFolderError(f"{path} differs from the summary that was written (its content no longer matches the "
                             "SHA-256 it records): edited or damaged")
    problem = _files_problem(summary.get("files", {}))
    if problem:
        raise RunFolderError(f"{path} has a malformed \"files\" record ({problem}): not a summary written by train.py")
    from engine.config import current_names  # a run recorded under an older name of a key reads as today's

    return {**summary, "settings": current_names(summary["settings"])}


def _files_problem(record) -> str | None:
    """What is malformed in a summary's "files" record (None: nothing): {name: {"bytes", "sha256"}}."""
    if not isinstance(record, dict):
        return f"a JSON {type(record).__name__}, not an object"
    for name, entry in record.items():
        if name not in RECORDABLE_FILES:
            return f"it names {name!r}, not a file a run writes"
        if (not isinstance(entry, dict) or not isinstance(entry.get("bytes"), int) or isinstance(entry["bytes"], bool)
                or not isinstance(entry.get("sha256"), str) or len(entry["sha256"]) != 64):
            return f"its entry for {name} is {json.dumps(entry)[:80]}, not a size and a SHA-256"
    return None
