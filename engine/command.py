"""What ``train.py`` needs as a command, apart from the science: one line instead of a traceback.

A run is refused, stopped or ended in one line with a status (0 trained, 2 refused, 1 a full disk or an
unwritable file, 130/143 stopped by SIGINT/SIGTERM), never a traceback:

- ``stop_early_on_signals()``: SIGINT or SIGTERM while the command loads and checks (before a run
  trains; ``engine.processes.StopSignals`` takes over while it trains);
- ``run(main)``: ``main`` (Hydra's app) with Hydra's own errors (``algo=nope``, ``seed=${oops}``)
  reported in one line;
- ``validated(cfg)``: the typed configuration, checked before anything is written;
- ``session(cfg)``: a context the run trains in: its folder, a sweep's stop file, the one-line
  ending of every refusal (``end``), Hydra's record of the run written once it starts, and the
  lines that report what was trained or skipped.

Light to import (the standard library; Hydra and the engine are imported where used), so that the
signal handlers are in place before torch loads.
"""

from __future__ import annotations

import re
import signal
import sys
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from engine.processes import deferred

_trained = False  # set once the runs have trained: a late signal then says so


def _stopped_early(number, frame) -> None:
    """SIGINT or SIGTERM before a run trains (while it loads, checks and prepares): one line, not a
    traceback; nothing of the run was written yet."""
    if deferred(number, frame):  # inside a library's code, or torch's maybe called from its C++: sent again shortly
        return
    name = signal.Signals(number).name
    if _trained:
        print(f"Stopped by {name} after training ended (its results are written)", file=sys.stderr)
    else:
        print(f"Stopped by {name} before training started; nothing was written: the same command starts the run",
              file=sys.stderr)
    raise SystemExit(130 if number == signal.SIGINT else 143)


_stopped_early.racing_replaceable = True  # engine.processes.replaceable


def stop_early_on_signals() -> None:
    """SIGINT and SIGTERM end the command in one line until a run takes them over (first of all: the
    imports that follow take seconds). An ignored signal stays ignored."""
    for number, default in ((signal.SIGINT, signal.default_int_handler), (signal.SIGTERM, signal.SIG_DFL)):
        if signal.getsignal(number) is default:
            signal.signal(number, _stopped_early)


class RunRefused(Exception):
    """A job of a sweep that did not run (or did not finish): Hydra records it as failed and the
    sweep goes on (``hydra_plugins/racing_launcher/sweeper.py`` lists every such job at the end)."""


def end(message: str, status: int, prefix: str = "Refusing to run: ", quiet: bool = False) -> None:
    """Print the one line (unless ``quiet``: the sweep's own line counts it) and end: the process's
    exit status, or a failed job in a sweep."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not quiet:
        print(f"{prefix}{message}", file=sys.stderr)
    if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
        raise RunRefused(f"{prefix}{message}")
    raise SystemExit(status)


def validated(cfg) -> tuple[dict, "RunConfig"]:  # noqa: F821
    """The composed configuration as plain settings and as a checked ``RunConfig``, the run's numerics
    applied (before torch loads: it reads the kernel settings then); a bad value, a run that cannot fit
    this machine or a bad ``$RACING_KERNEL_ISA`` ends the command in one line, nothing written."""
    from omegaconf.errors import OmegaConfBaseException

    from engine import numerics
    from engine.config import ConfigError, RunConfig, config_mapping
    from engine.limits import check_ram

    getattr(sys.stderr, "pass_through", lambda: None)()  # Hydra has composed the configuration (_HydraErrors)
    try:
        settings = config_mapping(cfg)
        run_cfg = RunConfig.from_mapping(settings)
        check_ram(run_cfg)
    except (ConfigError, OmegaConfBaseException) as err:  # e.g. seed=${oops}: an interpolation to nothing
        end(str(err).strip().splitlines()[0], 2, prefix="Invalid configuration: ")
    try:
        numerics.apply(run_cfg.numerics, run_cfg.threads)
    except numerics.NumericsError as err:
        end(str(err), 2)
    return settings, run_cfg


@dataclass
class Session:
    """Where a run trains and what it reports: ``out_dir`` (Hydra's run folder), ``root`` (a sweep's
    folder, every folder below it checked) and ``stop_file`` (a sweep's: a job stopped by a signal
    stops its sweep), ``skipped`` (members already finished) and ``started`` (called once the run is
    sure to start: writes Hydra's record of it)."""

    cfg: object
    settings: dict
    out_dir: Path
    root: Path | None = None
    stop_file: Path | None = None
    skipped: list = field(default_factory=list)

    def started(self) -> None:
        """Hydra's record of the run (``.hydra/config.yaml``, ``hydra.yaml``, ``overrides.yaml``), written
        atomically once the run is sure to start (Hydra writes none itself: conf/config.yaml)."""
        from hydra.core.hydra_config import HydraConfig
        from omegaconf import OmegaConf

        from door import files

        record = files.folder(self.out_dir / ".hydra", self.out_dir, create=True)  # a real folder, not a link
        hydra_cfg = HydraConfig.get()
        for name, node in (("config.yaml", self.cfg), ("hydra.yaml", OmegaConf.create({"hydra": hydra_cfg})),
                           ("overrides.yaml", hydra_cfg.overrides.task)):
            files.write_atomic(record / name, OmegaConf.to_yaml(node).encode(), root=self.out_dir)

    def report(self, run_cfg, summaries: list[dict]) -> None:
        """A line for each member skipped (already finished) and each run trained."""

        for folder, summary in self.skipped:
            print(skipped_line(folder, summary), file=sys.stderr)
        for summary in summaries:
            print(finished_line(run_cfg, self.out_dir, summary))


def skipped_line(folder, summary: dict) -> str:
    """The line of a member already finished, not trained again (by its run, or by its sweep's check)."""
    from engine.version import describe

    final = summary.get("final_mean")
    shown = f"{final:.1f}" if isinstance(final, (int, float)) else "none"  # as a finished run's line shows it
    return (f"{folder}: already {summary['status']} (final performance {shown}, {describe(summary.get('code'))}); "
            "skipped")


@contextmanager
def session(cfg, settings: dict):
    """The run's ``Session``; every way it can end early ends in one line (``end``): refused (2), a
    full disk or an unwritable file (1, the folder keeping its last good files), stopped by a signal
    (130/143: where it was saved; in a sweep, no further job starts)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from engine import numerics
    from engine.checkpoint import CheckpointError
    from engine.config import ConfigError
    from engine.processes import STOP_FILE, RunStopped, idle_between_jobs, read_stop_file, write_stop_file
    from door.files import DiskFull, FileRefused

    global _trained
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    here = Session(cfg, settings, out_dir)
    if HydraConfig.get().mode == RunMode.MULTIRUN:  # a sweep asked to stop starts no job, and stops its runs
        idle_between_jobs()  # a sweep's worker: a signal between its jobs is the sweep's, not the worker's end
        here.root = Path(HydraConfig.get().sweep.dir)  # every folder below it to the run's is checked (no link)
        here.stop_file = here.root / STOP_FILE
        asked = read_stop_file(here.stop_file)
        if asked is not None:
            end(f"the sweep was stopped by {asked} before this job started; the same command starts it", 2,
                prefix="Not started: ", quiet=True)
    try:
        yield here
    except DiskFull as err:
        end(str(err), 1, prefix="Stopped: ")
    except (ConfigError, CheckpointError, FileRefused, numerics.NumericsError) as err:  # FileRefused: the file door's
        end(str(err), 2)
    except RunStopped as stopped:
        if here.stop_file is not None:  # a job stopped by a signal stops its sweep: no further job starts
            write_stop_file(here.stop_file, "SIGINT" if "SIGINT" in str(stopped) else "SIGTERM")
        end(str(stopped), 130 if "SIGINT" in str(stopped) else 143, prefix="")
    except OSError as err:  # a file the run could not write, named by the system's error
        end(f"{err.strerror or err} ({err.filename or out_dir}); the folder keeps its last good files", 1,
            prefix="Stopped: ")
    _trained = True


def finished_line(cfg, out_dir: Path, summary: dict) -> str:
    """One line per run at the end (also where the output is a file): status, performance, folder."""
    folder = out_dir if cfg.seeds is None else out_dir / f"seed{summary['seed']}"
    final = summary.get("final_mean")
    score = (f"final performance {final:.1f} (mean total reward of the last {summary.get('final_window')} "
             "episodes)") if isinstance(final, (int, float)) else "no final performance"
    evaluated = summary.get("evaluation")
    tail = f", evaluated {evaluated['mean']:.1f} on eval_seeds" if evaluated else ""
    return (f"{summary['algo']}/{summary['er']} seed {summary['seed']}: {summary['status']} after "
            f"{summary['episodes']} episodes, {score}{tail}; results in {folder}")


class _HydraErrors:
    """stderr while Hydra composes the configuration, before ``main`` runs: what Hydra writes there is
    an error (``algo=nope``, ``nope=1``, ``episodes=[``: the message, the options, the config search
    path, a hint) that ``run`` reports in one line; its notice that it could not shorten a traceback
    is dropped. From ``validated`` on, everything passes through."""

    def __init__(self, stream):
        self.stream = stream
        self.held: list[str] | None = []

    def write(self, text: str) -> int:
        if text.startswith("An error occurred during Hydra's exception formatting"):
            return len(text)
        if self.held is not None:
            self.held.append(text)
            return len(text)
        return self.stream.write(text)

    def pass_through(self) -> None:
        held, self.held = self.held or [], None
        for text in held:
            self.stream.write(text)

    def line(self) -> str | None:
        """Hydra's error in one line: its first line, the options it lists, its hint (None: it wrote nothing)."""
        lines = [line.strip() for text in self.held or [] for line in text.splitlines() if line.strip()]
        lines = [line for line in lines if not line.startswith(("Set the environment variable HYDRA_FULL_ERROR",
                                                                "See https://hydra.cc"))]
        if not lines:
            return None
        first = lines[0]
        if first.startswith("Traceback (most recent call last)"):  # Hydra failed outside its own checks
            last = next((line for line in reversed(lines) if re.match(r"[A-Za-z_][\w.]*(Error|Exception)\b", line)),
                        lines[-1])
            kind, _, message = last.partition(": ")
            if kind in ("OSError", "PermissionError", "FileNotFoundError", "FileExistsError", "NotADirectoryError"):
                return f"the run's folder cannot be made or used ({message[:300]})"
            return last[:300]
        if "Available options" in " ".join(lines):
            start = next(i for i, line in enumerate(lines) if line.startswith("Available options")) + 1
            stop = next((i for i, line in enumerate(lines) if line.startswith("Config search path")), len(lines))
            first += f" (options: {', '.join(lines[start:stop])})"
        hint = next((line for line in lines if line.startswith("To append to your config use")), None)
        if hint:
            first += f" ({hint[0].lower()}{hint[1:]})"
        elif len(lines) > 1 and first.startswith("Could not"):
            first += f" ({lines[1]})"
        from engine.config import RENAMED_KEYS

        for (node, old), new in RENAMED_KEYS.items():  # a key given by the name it had before
            if f"'{node}.{old}'" in first:
                return f"{node}.{old} is called {node}.{new} now: give {node}.{new}=... instead"
        return first

    def __getattr__(self, name):
        return getattr(self.stream, name)


CODE_FROM_DATA = {"experimental_rerun": "--experimental-rerun"}  # Hydra's options that unpickle a file: {dest: flag}


def pickle_flag(argv: list[str]) -> str | None:
    """The flag among ``argv`` that would make Hydra unpickle a file (None: none), found as Hydra's own argument
    parser reads the command line, so any spelling it accepts counts (``--exp evil.pickle``: argparse takes any
    unique prefix of ``--experimental-rerun``; ``--experimental-rerun=...``), not a spelling of ours."""
    import argparse
    import contextlib
    import io

    from hydra._internal.utils import get_args_parser

    parser = get_args_parser()
    parser.exit_on_error = False
    try:
        with contextlib.redirect_stderr(io.StringIO()):  # a command line Hydra refuses: Hydra says why, later
            found, _ = parser.parse_known_args(argv)
    except (argparse.ArgumentError, SystemExit):
        return None
    return next((flag for dest, flag in CODE_FROM_DATA.items() if getattr(found, dest, None) is not None), None)


def run(main) -> None:
    """``main()`` (the Hydra app); a configuration Hydra cannot compose (``algo=nope``) or resolve
    (``seed=${oops}``, which its run folder's name interpolates) ends in one line and exit status 2,
    as other invalid configurations do."""
    from omegaconf.errors import OmegaConfBaseException

    from engine.processes import readable_output

    readable_output()  # a folder name that is not UTF-8 is printed escaped
    flag = pickle_flag(sys.argv[1:])  # Hydra's own flags that load pickles: code would run from a file
    if flag is not None:
        end(f"{flag} loads a pickled configuration, which can run code from a file; rerun a run with "
            "its command instead (its .hydra/overrides.yaml lists it)", 2)
    stderr = sys.stderr
    sys.stderr = errors = _HydraErrors(stderr)
    try:
        main()
    except OmegaConfBaseException as err:
        lines = [line.strip() for line in str(err).splitlines() if line.strip()]
        print(f"Invalid configuration: {lines[0] if lines else type(err).__name__}", file=stderr)
        errors.held = None  # said in that line
        raise SystemExit(2) from None
    except SystemExit as ending:
        line = errors.line()
        if line is not None and ending.code == 1:  # Hydra's own error, before main ran
            print(f"Invalid configuration: {line}", file=stderr)
            errors.held = None
            raise SystemExit(2) from None
        raise
    finally:
        errors.pass_through()
        sys.stderr = stderr
        for number in (signal.SIGINT, signal.SIGTERM):  # the work is over: a late signal must not interrupt
            if signal.getsignal(number) is _stopped_early:  # the exit (joblib joins its threads at exit)
                signal.signal(number, signal.SIG_IGN)
