"""What a run leaves in its folder: metrics.csv, summary.json, weights, and TorchRL logs."""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path
from typing import Any

METRICS_FILE = "metrics.csv"
SUMMARY_FILE = "summary.json"
EPISODE_COLUMNS = ("episode", "total_reward", "crashes", "final_checkpoint")


class RunFolderError(ValueError):
    """A folder that does not hold a usable trained run."""


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
        self.file = open(self.path, "w", newline="")
        self.writer = csv.DictWriter(self.file, fieldnames=columns, extrasaction="raise")
        self.writer.writeheader()
        self.file.writelines(kept)
        self.file.flush()
        self.logger = make_torchrl_logger(logger_kind, out_dir)

    def _kept_rows(self, count: int) -> list[str]:
        if count == 0:
            return []
        try:
            with open(self.path, newline="") as f:  # keep the csv module's line endings
                lines = f.read().splitlines(keepends=True)
        except FileNotFoundError:
            lines = []
        if len(lines) < count + 1 or lines[0].rstrip("\r\n") != ",".join(self.columns):
            raise RuntimeError(f"{self.path} does not hold the {count} episodes its checkpoint has; "
                               "delete the checkpoint to start the run afresh")
        return lines[1:count + 1]

    def write(self, row: dict[str, Any]) -> None:
        self.writer.writerow({key: _format(row.get(key)) for key in self.columns})
        self.file.flush()
        if self.logger is not None:
            step = int(row["episode"])
            for key, value in row.items():
                if key != "episode" and value is not None:
                    self.logger.log_scalar(f"train/{key}", float(value), step=step)

    def close(self) -> None:
        self.file.close()


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


def write_json_atomic(path: Path, data: dict) -> None:
    """Write ``data`` as JSON to a temporary file, then rename it over ``path``."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        json.dump(data, f, indent=2, sort_keys=False)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def read_summary(out_dir: Path) -> dict | None:
    """The run's summary.json, or ``None`` if it has none (or an unreadable one)."""
    try:
        return json.loads((out_dir / SUMMARY_FILE).read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None
