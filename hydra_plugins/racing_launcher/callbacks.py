"""Hydra's own writes, checked before Hydra makes them (``conf/config.yaml``'s ``hydra.callbacks``).

Hydra writes a few files itself before ``train.py`` runs: its record of the configuration under
``hydra.output_subdir`` and the log files of ``hydra.job_logging``/``hydra.hydra_logging``. It
opens them by name, through any link, outside the file door (``door/files.py``). This project
turns them off (``train.py`` writes ``.hydra/`` itself through the door; no log file), and this
callback refuses a command that turns them back on, before any folder is made or file written.
"""

from __future__ import annotations

import sys
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf


class HydraWrites(Callback):
    """Refuse (one line, exit status 2, before anything is written) a configuration under which
    Hydra itself would write a file: a record (``hydra.output_subdir`` not null) or a log file.
    (Hydra turns a callback's exceptions into warnings and goes on: the refusal is a ``SystemExit``.)"""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        _refuse(config)

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        _refuse(config)


def _refuse(config: DictConfig) -> None:
    try:
        check(config)
    except ValueError as err:
        print(f"Invalid configuration: {err}", file=sys.stderr)
        raise SystemExit(2) from None


def check(config: DictConfig) -> None:
    """``ValueError`` saying which setting would make Hydra write a file itself (None: none would)."""
    hydra = config.hydra
    if hydra.output_subdir is not None:
        raise ValueError(f"hydra.output_subdir must stay null (it is {hydra.output_subdir!r}): train.py writes the "
                         "run's record in .hydra/ itself, through the project's checks; Hydra's own would write "
                         "through links")
    for key in ("job_logging", "hydra_logging"):
        node = OmegaConf.to_container(hydra[key], resolve=False) if hydra.get(key) is not None else {}
        files = [name for name, handler in (node.get("handlers") or {}).items()
                 if isinstance(handler, dict) and "filename" in handler]
        if files:
            raise ValueError(f"hydra.{key} writes a log file (handlers {files}): this project keeps no Hydra log file "
                             "(its files go through its own checks); use a logging setup without file handlers")
