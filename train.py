"""Train one cell of the paper's table: ``python train.py algo=spg_p er=hybrid seed=3``, or one
run per seed in one process: ``python train.py algo=spg_p er=hybrid 'seeds=[3,4,5]'``.

A run writes into its folder (``outputs/runs/<algo>/<er>/seed<seed>`` by default, or the
sweep's subfolder with ``-m``): ``metrics.csv``, ``summary.json``, ``actor.pt``, ``critic.pt``,
TorchRL logs and the resolved configuration in ``.hydra/`` (written once the run is sure to
start: a refused command leaves the folder as it was). With ``seeds``, each member writes that
into ``outputs/runs/<algo>/<er>/seed<seed>/``. See ``conf/config.yaml`` for every option and
``engine/rundir.py`` for the rules of a run folder (finished, resumable, damaged; its lock).

Exit status: 0 when every run finished (its last line says where and how well), 2 when the
command was refused (one line saying why; nothing was written), 1 for a full disk, 130 or 143
when stopped by SIGINT or SIGTERM (one line: where it was saved; the same command resumes).
"""

from __future__ import annotations

import os
import re
import signal
import sys
from pathlib import Path

from engine.processes import deferred  # light (the standard library): before the handlers need it


def _stopped_early(number, frame) -> None:
    """SIGINT or SIGTERM before a run trains (while it loads, checks and prepares): one line, not a
    traceback; nothing of the run was written yet (``engine.processes.StopSignals`` takes over
    while it trains)."""
    if deferred(number, frame):  # inside torch's Python code, maybe called from its C++: sent again shortly
        return
    name = signal.Signals(number).name
    if _trained:
        print(f"Stopped by {name} after training ended (its results are written)", file=sys.stderr)
    else:
        print(f"Stopped by {name} before training started; nothing was written: the same command starts the run",
              file=sys.stderr)
    raise SystemExit(130 if number == signal.SIGINT else 143)


_trained = False  # set once train_population has returned
_stopped_early.racing_replaceable = True  # engine.processes.replaceable, without importing it first
if __name__ == "__main__":  # first of all: the imports below take seconds
    for _number, _default in ((signal.SIGINT, signal.default_int_handler), (signal.SIGTERM, signal.SIG_DFL)):
        if signal.getsignal(_number) is _default:  # an ignored signal stays ignored
            signal.signal(_number, _stopped_early)

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from engine import numerics
from engine.config import ConfigError, RunConfig, config_mapping, register_resolvers
from engine.limits import check_memory
from racing.files import DiskFull, FileRefused

os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")  # torchrl's INFO lines (set before it loads)
register_resolvers()  # the run folder's name (conf/config.yaml) uses one


class RunRefused(Exception):
    """A job of a sweep that did not run (or did not finish): Hydra records it as failed and the
    sweep goes on (``hydra_plugins/racing_launcher/sweeper.py`` lists every such job at the end)."""


def _end(message: str, status: int, prefix: str = "Refusing to run: ", quiet: bool = False) -> None:
    """Print the one line (unless ``quiet``: the sweep's own line counts it) and end: the process's
    exit status, or a failed job in a sweep."""
    if not quiet:
        print(f"{prefix}{message}", file=sys.stderr)
    if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
        raise RunRefused(f"{prefix}{message}")
    raise SystemExit(status)


def save_hydra_record(cfg: DictConfig, out_dir: Path) -> None:
    """Hydra's record of the run (``.hydra/config.yaml``, ``hydra.yaml``, ``overrides.yaml``), written
    atomically once the run is sure to start (``hydra.output_subdir: null`` stops Hydra's own)."""
    from racing import files

    record = files.folder(out_dir / ".hydra", out_dir, create=True)  # a real folder of the run's, not a link
    hydra_cfg = HydraConfig.get()
    for name, node in (("config.yaml", cfg), ("hydra.yaml", OmegaConf.create({"hydra": hydra_cfg})),
                       ("overrides.yaml", hydra_cfg.overrides.task)):
        files.write_atomic(record / name, OmegaConf.to_yaml(node).encode(), root=out_dir)


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float | list | None:
    getattr(sys.stderr, "pass_through", lambda: None)()  # Hydra has composed the configuration (_HydraErrors)
    try:
        settings = config_mapping(cfg)
        run_cfg = RunConfig.from_mapping(settings)
        check_memory(run_cfg)  # before anything is written: a run that cannot fit does not start
    except (ConfigError, OmegaConfBaseException) as err:  # e.g. seed=${oops}: an interpolation to nothing
        _end(str(err).strip().splitlines()[0], 2, prefix="Invalid configuration: ")
    try:
        numerics.apply(run_cfg.numerics)  # before torch loads: it reads the kernel settings then
    except numerics.NumericsError as err:  # also a bad $RACING_KERNEL_ISA
        _end(str(err), 2)
    from engine.checkpoint import CheckpointError
    from engine.processes import RunStopped
    from engine.runner import train_population  # after validation: torch loads slowly
    from engine.version import describe

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    stop_file, root = None, None
    if HydraConfig.get().mode == RunMode.MULTIRUN:  # a sweep asked to stop starts no job, and stops its runs
        from engine.processes import STOP_FILE, idle_between_jobs, read_stop_file

        idle_between_jobs()  # a sweep's worker: a signal between its jobs is the sweep's, not the worker's end

        root = Path(HydraConfig.get().sweep.dir)  # every folder below it to the run's is checked (no link)
        stop_file = root / STOP_FILE
        asked = read_stop_file(stop_file)
        if asked is not None:
            _end(f"the sweep was stopped by {asked} before this job started; the same command starts it", 2,
                 prefix="Not started: ", quiet=True)
    skipped: list[tuple[Path, dict]] = []
    try:
        summaries = train_population(run_cfg, out_dir, settings, skipped=skipped,
                                     on_start=lambda: save_hydra_record(cfg, out_dir), stop_file=stop_file,
                                     root=root)
    except DiskFull as err:
        _end(str(err), 1, prefix="Stopped: ")
    except (ConfigError, CheckpointError, FileRefused, numerics.NumericsError) as err:  # FileRefused: the file door's
        _end(str(err), 2)
    except RunStopped as stopped:
        if stop_file is not None:  # a job stopped by a signal stops its sweep: no further job starts
            from engine.processes import write_stop_file

            write_stop_file(stop_file, "SIGINT" if "SIGINT" in str(stopped) else "SIGTERM")
        _end(str(stopped), 130 if "SIGINT" in str(stopped) else 143, prefix="")
    except OSError as err:  # a file the run could not write, named by the system's error
        _end(f"{err.strerror or err} ({err.filename or out_dir}); the folder keeps its last good files", 1,
             prefix="Stopped: ")
    global _trained
    _trained = True
    for folder, summary in skipped:
        print(f"{folder}: already {summary['status']} (final_mean {summary['final_mean']}, "
              f"{describe(summary.get('code'))}); skipped", file=sys.stderr)
    for summary in summaries:
        print(_finished_line(run_cfg, out_dir, summary))
    finals = [s["final_mean"] for s in summaries]
    return finals[0] if run_cfg.seeds is None else finals


def _finished_line(cfg: RunConfig, out_dir: Path, summary: dict) -> str:
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
    path, a hint) that ``_run`` reports in one line; its notice that it could not shorten a traceback
    is dropped. From ``main``'s first line on, everything passes through."""

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
            end = next((i for i, line in enumerate(lines) if line.startswith("Config search path")), len(lines))
            first += f" (options: {', '.join(lines[start:end])})"
        hint = next((line for line in lines if line.startswith("To append to your config use")), None)
        if hint:
            first += f" ({hint[0].lower()}{hint[1:]})"
        elif len(lines) > 1 and first.startswith("Could not"):
            first += f" ({lines[1]})"
        return first

    def __getattr__(self, name):
        return getattr(self.stream, name)


def _run() -> None:
    """``main()``; a configuration Hydra cannot compose (``algo=nope``) or resolve (``seed=${oops}``,
    which its run folder's name interpolates) ends in one line and exit status 2, as other invalid
    configurations do."""
    from engine.processes import readable_output

    readable_output()  # a folder name that is not UTF-8 is printed escaped
    stderr = sys.stderr
    sys.stderr = errors = _HydraErrors(stderr)
    try:
        main()
    except OmegaConfBaseException as err:
        lines = [line.strip() for line in str(err).splitlines() if line.strip()]
        print(f"Invalid configuration: {lines[0] if lines else type(err).__name__}", file=stderr)
        errors.held = None  # said in that line
        raise SystemExit(2) from None
    except SystemExit as end:
        line = errors.line()
        if line is not None and end.code == 1:  # Hydra's own error, before main ran
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


if __name__ == "__main__":
    _run()
