"""The sweeper of ``-m`` (``hydra/sweeper=checked``, the default in conf/config.yaml): Hydra's
basic sweeper (the same jobs, in the same order, through any launcher) that checks the whole sweep
before its first job starts and accounts for every job when it ends.

Before any job starts, every job's configuration is composed and validated as train.py would
(``engine.config.RunConfig``), and every job's run folder is checked (``engine.rundir``): two jobs
writing one folder, a folder holding a finished run of another configuration or a damaged one
(unless ``overwrite=true``), a folder another process is training in. All problems are listed at
once, one line per job, and nothing runs (exit status 2). A checkpoint's configuration is not
checked here (that needs torch); its job refuses it alone. A long check says how far it is every ten
seconds. A job whose every member already holds a finished run of the job's own settings is not
launched: its members' lines say they are skipped, as the job would have said.

When the jobs have run, those that failed (refused, stopped, or raised) are listed one line each
with their message, after the others have finished; the command then exits with status 1. (The
SLURM launcher reports its failures itself, the same way.)

SIGINT or SIGTERM to the sweep's process (Ctrl-C, ``timeout``, a scheduler) stops the sweep as it
stops a run: the sweep's folder gets a stop file (``engine.processes.STOP_FILE``) that every
running job sees at its episode's end (it saves its checkpoint and stops) and every job not yet
started sees before it starts (it does not start); the sweep then ends with one line and exit
status 130 or 143, and no process of it is left. A second signal stops the running jobs at once
(they resume from their last checkpoints). The same command resumes the sweep.
"""

from __future__ import annotations

import copy
import logging
import os
import signal
import sys
from pathlib import Path
from typing import Any

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.utils import JobStatus, filter_overrides
from omegaconf import OmegaConf, open_dict
from omegaconf.errors import OmegaConfBaseException


class SweepRefused(SystemExit):
    """The sweep did not start: some jobs' configurations or folders are bad (listed)."""


class SweepJobsFailed(SystemExit):
    """Some jobs of the sweep failed (listed); the others' results are in their folders."""


class SweepStopped(SystemExit):
    """The sweep was stopped by a signal; its jobs saved their checkpoints (one line said so)."""


class _SweepSignals:
    """For the sweep: the first SIGINT or SIGTERM writes the stop file; a second one is passed on to
    every process the sweep started (their runs stop at once). Runs that train in this process
    (Hydra's basic launcher) stand in for these handlers while they train (``replaceable``)."""

    def __init__(self, stop_file: Path):
        self.stop_file = stop_file
        self.requested: str | None = None
        self._previous: dict = {}

    def _handle(self, number, frame) -> None:
        from engine.processes import descendants, stop_at_once, write_stop_file

        name = signal.Signals(number).name
        if self.requested is None:
            self.requested = name
            write_stop_file(self.stop_file, name)
            return
        stop_at_once(descendants())

    def __enter__(self) -> "_SweepSignals":
        from engine.processes import replaceable

        handler = replaceable(self._handle)
        for number in (signal.SIGINT, signal.SIGTERM):
            if signal.getsignal(number) is not signal.SIG_IGN:
                self._previous[number] = signal.signal(number, handler)
        return self

    def __exit__(self, *exc) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)


DATED_SWEEP_DIR = "outputs/sweeps/${now:%Y-%m-%d_%H-%M-%S}"  # Hydra's usual default, which conf/config.yaml keeps


def sweep_folder_name(arguments: list[str]) -> str:
    """The folder of an ad-hoc sweep, named by its command line: the same command, the same folder (so
    running it again continues it), readable, and short enough for any file system."""
    import hashlib
    import re

    text = " ".join(arguments) or "defaults"
    readable = re.sub(r"[^A-Za-z0-9._+-]+", "_", text.replace("=", "-").replace(",", "+")).strip("._") or "sweep"
    return f"{readable[:80]}-{hashlib.sha256(text.encode()).hexdigest()[:8]}"


class _JoblibSettings(logging.Filter):
    """Drops the joblib launcher's line of raw settings (``Joblib.Parallel(n_jobs=-1,backend=loky,...)``):
    the lines after it say which jobs run where."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Joblib.Parallel(")


class CheckedSweeper(BasicSweeper):
    def sweep(self, arguments: list[str]) -> Any:
        assert self.config is not None and self.launcher is not None and self.hydra_context is not None
        joblib_log = logging.getLogger("hydra_plugins.hydra_joblib_launcher._core")
        if not any(isinstance(f, _JoblibSettings) for f in joblib_log.filters):
            joblib_log.addFilter(_JoblibSettings())
        getattr(sys.stderr, "pass_through", lambda: None)()  # composed: train.py's stderr is the sweep's now
        _name_the_folder(self.config, arguments)
        parser = OverridesParser.create(config_loader=self.hydra_context.config_loader)
        self.overrides = self.split_arguments(parser.parse_overrides([*self._parse_config(), *arguments]),
                                              self.max_batch_size)
        jobs = [list(job) for batch in self.overrides for job in batch]
        self.folders: list[list[Path]] = []
        folder_problem = sweep_dir_problem(self.config) or environment_problem()  # before any job's folder
        if folder_problem:
            print(f"The sweep was not started: {folder_problem}", file=sys.stderr)
            raise SweepRefused(2)
        finished: dict[int, list] = {}
        problems = check_jobs(self.hydra_context.config_loader, self.config, jobs, self.folders, finished)
        if not problems:
            _say_finished(finished)
        if problems:
            print(f"The sweep was not started: {len(problems)} of its {len(jobs)} jobs cannot run as given "
                  "(nothing was written):", file=sys.stderr)
            print("\n".join(f"  {line}" for line in problems), file=sys.stderr)
            raise SweepRefused(2)
        from engine.config import NOTES_SAID

        os.environ[NOTES_SAID] = "1"  # every job's configuration notes were said by the check: not again per job
        from engine.processes import STOP_FILE, read_stop_file

        from door import files

        try:
            sweep_dir = files.folder(Path(str(self.config.hydra.sweep.dir)), create=True)
            stop_file = sweep_dir / STOP_FILE
            for name in ("multirun.yaml", STOP_FILE):  # the sweep's own files: each a file, or nothing yet
                if os.path.lexists(sweep_dir / name) and not files.is_file(sweep_dir / name) \
                        and not (sweep_dir / name).is_symlink():
                    raise files.FileRefused(f"{sweep_dir / name} is {files.kind(os.lstat(sweep_dir / name).st_mode)} "
                                            "where the sweep keeps its own file: move it away")
            files.write_atomic(sweep_dir / "multirun.yaml", OmegaConf.to_yaml(self.config).encode())  # never through a link
            files.remove(stop_file)  # an earlier sweep's: this one starts anew
        except (OSError, files.FileRefused) as err:
            print(f"The sweep was not started: {err}", file=sys.stderr)
            raise SweepRefused(2) from None
        returns, failed, first = [], [], 0
        with _SweepSignals(stop_file):
            while not self.is_done() and read_stop_file(stop_file) is None:
                batch = self.get_job_batch()
                results = []
                for start, part in _unfinished_runs(batch, first, finished):  # a finished job is not launched
                    try:
                        results += self.launcher.launch(part, initial_job_idx=start)
                    except (Exception, KeyboardInterrupt):  # a second signal reached jobs that were starting
                        if read_stop_file(stop_file) is None:
                            raise
                        break
                    for index, (job, result) in enumerate(zip(part, results[-len(part):]), start=start):
                        if result.status == JobStatus.FAILED:
                            failed.append(f"job #{index} ({' '.join(filter_overrides(job))}): "
                                          f"{_message(result._return_value)}")
                first += len(batch)
                returns.append(results)
        stopped = read_stop_file(stop_file)
        files.remove(stop_file)  # every job has ended: the next sweep starts anew
        if stopped is not None:  # counted from the folders: a job's own report may not have come back
            from engine import rundir

            states = [[rundir.state(f).kind for f in paths] for paths in self.folders]  # the job's, its members'
            done = sum(bool(kinds) and set(kinds[1:] or kinds) == {"finished"} for kinds in states)
            saved = sum("resumable" in kinds for kinds in states)
            print(f"Sweep stopped by {stopped}: {done} of {len(jobs)} jobs finished, {saved} stopped with a "
                  f"checkpoint, {len(jobs) - done - saved} not started or not saved: the same command resumes it",
                  file=sys.stderr)
            raise SweepStopped(130 if stopped == "SIGINT" else 143)
        if failed:
            print(f"{len(failed)} of {len(jobs)} jobs did not finish; the others' results are in their folders "
                  "(the same command skips those and retries these):", file=sys.stderr)
            print("\n".join(f"  {line}" for line in failed), file=sys.stderr)
            raise SweepJobsFailed(1)
        return returns

    def validate_batch_is_legal(self, batch) -> None:
        """Done for the whole sweep at once, before it starts (``check_jobs``)."""


def _resolves_with_launcher_values(cfg) -> bool:
    """Whether the job's folder name resolves once the values a launcher sets as the job starts (its id, a
    scheduler's job id) stand in: if not, it fails for another reason (an environment variable that is not
    set, a key that does not exist) and every job would end in a traceback."""
    probe = copy.deepcopy(cfg)
    with open_dict(probe):
        probe.hydra.job.id = "job-id"
        probe.hydra.job.name = probe.hydra.job.name or "train"
    try:
        OmegaConf.select(probe, "hydra.sweep.subdir")
    except Exception:  # noqa: BLE001 (any resolution error: what it is, the caller says)
        return False
    return True


def _unfinished_runs(batch: list, first: int, finished: dict) -> list[tuple[int, list]]:
    """(first job index, jobs) for each unbroken run of jobs of ``batch`` (numbered from ``first``) that
    are not finished: launched as such, each job keeps its number (a folder name may use it)."""
    runs: list[tuple[int, list]] = []
    for index, job in enumerate(batch, start=first):
        if index in finished:
            continue
        if runs and runs[-1][0] + len(runs[-1][1]) == index:
            runs[-1][1].append(job)
        else:
            runs.append((index, [job]))
    return runs


def _say_finished(finished: dict) -> None:
    """The line each skipped member gets (as a job that started would print it), for the jobs not launched."""
    from engine.command import skipped_line

    for index in sorted(finished):
        for folder, summary in finished[index]:
            print(skipped_line(folder, summary), file=sys.stderr)


def _first_line(error: Any) -> str:
    """The first line of a composition error (Hydra's list the config search path after it)."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return (lines[0] if lines else type(error).__name__)[:300]


def _message(error: Any) -> str:
    lines = [line for line in str(error).splitlines() if line.strip()]
    return (lines[-1] if lines else type(error).__name__)[:300]


def check_jobs(loader, master, jobs: list[list[str]], folders: list | None = None,
               finished: dict | None = None) -> list[str]:
    """One line per problem of the sweep's jobs (see the module's docstring); none if all can run.
    ``folders``, if given, receives each job's member folders (a list per job; empty where unknown);
    ``finished``, if given, {job index: [(member folder, summary)]} for the jobs whose every member holds
    a finished run of the job's own settings (nothing left to do)."""
    from engine import rundir
    from engine.config import ConfigError, RunConfig, config_mapping, register_resolvers
    from engine.limits import check_ram

    register_resolvers()
    folder_problem = sweep_dir_problem(master)
    if folder_problem:
        return [folder_problem]
    sweep_dir = Path(str(master.hydra.sweep.dir))
    problems: list[str] = []
    owners: dict[Path, str] = {}
    for index, job in enumerate(jobs):
        label = f"job #{index} ({' '.join(filter_overrides(job))})"
        try:
            cfg = loader.load_sweep_config(master, job)
        except Exception as err:  # Hydra's composition errors (unknown keys, groups, syntax)
            problems.append(f"{label}: {_first_line(err)}")
            continue
        try:
            with open_dict(cfg):
                cfg.hydra.job.num = index  # as the launcher numbers the jobs (a folder name may use it)
            subdir = str(OmegaConf.select(cfg, "hydra.sweep.subdir"))
        except Exception as err:  # a folder name that needs other launcher values (e.g. a SLURM job id)?
            subdir = None
            template = str(OmegaConf.to_container(cfg.hydra.sweep, resolve=False).get("subdir", ""))
            if template.startswith("/") or ".." in Path(template).parts:
                problems.append(f"{label}: its folder {template!r} (hydra.sweep.subdir) is not a folder inside the "
                                f"sweep's {sweep_dir}: it holds '..' or is an absolute path")
                continue
            if not _resolves_with_launcher_values(cfg):  # not for want of those: no launcher could name it
                problems.append(f"{label}: its folder {template!r} (hydra.sweep.subdir) cannot be resolved: "
                                f"{_first_line(err)}")
                continue
        with open_dict(cfg):
            del cfg["hydra"]
        try:
            settings = config_mapping(cfg)
            run_cfg = RunConfig.from_mapping(settings)
            check_ram(run_cfg)
        except (ConfigError, ValueError, TypeError, OmegaConfBaseException) as err:
            problems.append(f"{label}: invalid configuration: {_first_line(err)}")
            continue
        if subdir is None:
            continue
        folder = Path(os.path.abspath(sweep_dir / subdir))  # ".." taken out: folders that alias each other meet
        if not folder.is_relative_to(os.path.abspath(sweep_dir)) or folder == Path(os.path.abspath(sweep_dir)):
            problems.append(f"{label}: its folder {subdir!r} (hydra.sweep.subdir) is not a folder inside the sweep's "
                            f"{sweep_dir}: a configuration value there holds '..' or an absolute path")
            continue
        members = {seed: folder if run_cfg.seeds is None else folder / f"seed{seed}" for seed in run_cfg.members}
        if folders is not None:
            folders.append([folder, *(p for p in members.values() if p != folder)])
        for path in dict.fromkeys([folder, *members.values()]):
            if path in owners:
                problems.append(f"{label}: writes {path}, as {owners[path]} does; give the jobs different folders "
                                "(hydra.sweep.subdir) or remove the repeated value")
                break
            owners[path] = label
        else:
            problem = _folder_problem(rundir, RunConfig, run_cfg, settings, folder, members, sweep_dir)
            if problem:
                problems.append(f"{label}: {problem}")
            elif finished is not None and not run_cfg.overwrite:
                states = [rundir.state(path) for path in members.values()]
                if all(found.kind == "finished" for found in states):  # of these settings: _folder_problem says
                    finished[index] = [(found.folder, found.summary) for found in states]
        _say_progress(index + 1, len(jobs))
    return problems


_progress = {"last": None}


def _say_progress(done: int, total: int, every: float = 10.0) -> None:
    """A line every ``every`` seconds while a long check runs (1,000 jobs take about a minute)."""
    import time

    now = time.monotonic()
    if _progress["last"] is None or done == 1:
        _progress["last"] = now
    elif now - _progress["last"] >= every and done < total:
        _progress["last"] = now
        print(f"Checking the sweep's jobs before any starts: {done:,} of {total:,} checked", file=sys.stderr,
              flush=True)


def _folder_problem(rundir, RunConfig, run_cfg, settings: dict, folder: Path, members: dict,
                    sweep_dir: Path) -> str | None:
    """Why a job's folders would refuse it (None if they would not); writes nothing (no lock is
    taken: ``rundir.in_use`` only asks)."""
    from door import files

    for path in [folder, *members.values()]:  # no link from the sweep's folder down, before anything else
        try:
            files.check_chain(path, sweep_dir)
        except (OSError, files.FileRefused) as err:
            return str(err)
    training = RunConfig.run_settings(settings)
    for seed, path in members.items():
        if run_cfg.overwrite:
            break
        problem = rundir.refusal(rundir.state(path), run_cfg.member_settings(training, seed), solo=path == folder)
        if problem:
            return problem
    for path in dict.fromkeys([folder, *members.values()]):
        holder = rundir.in_use(path)
        if holder:
            return holder
    return None


def environment_problem() -> str | None:
    """What is wrong with the environment variables every job reads (``$RACING_KERNEL_ISA``), checked once for
    the whole sweep before any folder exists (each job would refuse it only after Hydra made its folder)."""
    from learners import kernels

    try:
        kernels.isa_cap()
    except kernels.KernelError as err:
        return str(err)
    return None


def sweep_dir_problem(master) -> str | None:
    """Why the sweep's folder cannot be resolved before its jobs (None: it can), e.g. ``${hydra:...}``,
    which Hydra sets only inside a job."""
    try:
        str(master.hydra.sweep.dir)
    except OmegaConfBaseException as err:
        return (f"hydra.sweep.dir: {_first_line(err)} (the sweep's folder is resolved before any job: give a "
                "path, or interpolations of the configuration)")
    return None


def _name_the_folder(config, arguments: list[str]) -> None:
    """A sweep left at the dated default folder (no ``hydra.sweep.dir`` given, by the command or its
    experiment) goes to ``outputs/sweeps/<its command line>`` instead (``sweep_folder_name``), given to its
    jobs as if on the command line."""
    given = OmegaConf.to_container(config.hydra.sweep, resolve=False).get("dir")
    if given != DATED_SWEEP_DIR:
        return
    folder = f"outputs/sweeps/{sweep_folder_name(arguments)}"
    with open_dict(config):
        config.hydra.sweep.dir = folder
        config.hydra.overrides.hydra.append(f"hydra.sweep.dir={folder}")
