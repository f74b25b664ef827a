"""A run folder's state, its lock, and how it is cleared: the one rule that train.py, evaluate.py,
report.py, the baselines and the sweeper apply (torch-free).

A run folder (a solo run's, or one member's of a population) is in one of four states:

- ``finished``: ``summary.json`` is a summary written by train.py (a JSON object with its keys)
  whose status is final, and the files it records (``metrics.csv``, ``actor.pt``, ``critic.pt``:
  size and SHA-256) are there unchanged (summaries from before the record: those files exist and
  are not empty);
- ``resumable``: no summary, and a checkpoint (``checkpoint*.pt``) to continue from; whether it
  loads and belongs to this configuration is ``engine.checkpoint``'s check;
- ``empty``: nothing but what a run writes before its first checkpoint (``metrics.csv`` rows,
  TorchRL logs, Hydra's record): starting afresh loses nothing that could be resumed;
- ``damaged``: anything else (a ``summary.json`` that is not one, files that differ from what the
  summary records, weights without a summary). Never taken for empty: a run refuses it, naming the
  file and the reason, unless ``overwrite=true`` clears it.

A process holds ``lock(folders)`` for the whole life of a run: an exclusive ``flock`` on each
folder's ``.lock`` file (the holder's pid written in it), taken without waiting, so a second
process on the same folder is refused at once; the kernel releases it when the holder ends,
however it ends.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import socket
import stat
from dataclasses import dataclass
from pathlib import Path

from door import files
from engine.outputs import (DIGEST_KEY, FINAL_STATUSES, METRICS_FILE, SUMMARY_FILE, RunFolderError, file_digest,
                            first_line, read_summary)

WEIGHT_FILES = ("actor.pt", "critic.pt")
RECORDED_FILES = (METRICS_FILE, *WEIGHT_FILES)  # what a summary's "files" record covers
LOCK_FILE = ".lock"
LOGS_DIR = "logs"  # TorchRL's logger (engine.outputs.make_torchrl_logger)
_CHECKPOINT_NAME = re.compile(r"checkpoint(-\d+)?\.pt")


class RunFolderBusy(RunFolderError):
    """Another process holds the folder's lock."""


@dataclass(frozen=True)
class FolderState:
    kind: str  # "empty", "finished", "resumable" or "damaged"
    folder: Path
    summary: dict | None = None  # a finished run's
    problem: str | None = None  # a damaged folder's: the file and what is wrong with it

    def refusal(self) -> str:
        """Why a run will not start in this damaged folder, and what to do."""
        return (f"{self.folder} is damaged: {self.problem}. Its files are left as they are; move them away, or "
                "pass overwrite=true to clear the folder and start afresh")


def refusal(found: FolderState, settings: dict | None, solo: bool = True) -> str | None:
    """Why a new run of ``settings`` may not start in ``found``'s folder without ``overwrite=true``
    (None: it may; a finished run of these very settings is skipped, not refused). ``solo=False``:
    the folder is a population member's, where a solo run's checkpoint is another run."""
    from engine.config import RunConfig, settings_difference

    if found.kind == "finished" and not RunConfig.same_run(found.summary.get("settings"), settings):
        return (f"{found.folder} holds a finished run of a different configuration "
                f"({settings_difference(found.summary.get('settings'), settings)}); choose another folder "
                "(hydra.run.dir=..., or hydra.sweep.dir=... for a sweep) or pass overwrite=true to replace it")
    if found.kind == "damaged":
        return found.refusal()
    if found.kind == "resumable" and not solo:
        return (f"{found.folder} holds the checkpoint of a solo run of its seed; resume it with that run's "
                "command, or pass overwrite=true to start this population afresh")
    return None


_RUN_NAMES = (SUMMARY_FILE, *RECORDED_FILES, "model.zip", LOCK_FILE, LOGS_DIR, ".hydra")
RUN_MARKS = (SUMMARY_FILE, METRICS_FILE, ".hydra")  # with its checkpoints: what only a run's folder holds


def _is_run_file(name: str) -> bool:
    """A name a run writes in its folder (a user's ``checkpoint-copy.pt`` or ``notes.tmp`` is not)."""
    return name in _RUN_NAMES or _CHECKPOINT_NAME.fullmatch(name) is not None


def holds_a_run(folder) -> bool:
    """Whether ``folder`` carries a run's marks, whatever state the run is in: its summary, rows,
    checkpoints or Hydra's record (a population's top folder, with ``.hydra/``, is one; a sweep's, with
    ``multirun.yaml``, is not; a ``.lock``, ``logs/`` or weights alone are not: a downloaded ``model.zip`` or
    ``actor.pt`` sits anywhere, and other programs name their locks and logs so too).
    The one answer every tool asks before it writes."""
    try:
        names = os.listdir(folder)
    except OSError:
        return False
    return any(name in RUN_MARKS or _CHECKPOINT_NAME.fullmatch(name) for name in names)


def training_budget(summary: dict) -> int:
    """The episodes a finished run was planned for (its summary's ``episodes_planned``; the episodes it ran,
    for summaries written before that key): what runs of one budget have in common."""
    return int(summary.get("episodes_planned") or summary["episodes"])


def run_folder_of(path) -> Path | None:
    """The run folder ``path`` lies in (the nearest folder at or above it that ``holds_a_run``), or None."""
    folder = Path(os.path.abspath(path))
    for candidate in (folder, *folder.parents):
        if holds_a_run(candidate):
            return candidate
    return None


def _run_files(folder: Path) -> list[Path]:
    """Every file (and folder) a run writes in its folder: those of fixed names, present or not, and
    its checkpoints present (files or links)."""
    return [folder / name for name in _RUN_NAMES] + sorted(
        p for p in folder.glob("checkpoint*.pt") if _is_run_file(p.name))


def linked_file(folder: Path) -> str | None:
    """What is where a run keeps its own files and is not one of them (None: nothing): a symbolic
    link, a FIFO, a device or a folder at a file's name, a file at a folder's name, or anything
    below ``logs/`` or ``.hydra/`` that is a link, a special file or a hard link (TorchRL's loggers
    open their files themselves: their folder is checked whole, ``door.files.check_tree``)."""
    folder = Path(folder)
    for path in _run_files(folder):
        try:
            info = os.lstat(path)
        except OSError:
            continue
        if stat.S_ISLNK(info.st_mode):
            return (f"{path} is a symbolic link where a run keeps its own file (a run never reads or writes through a "
                    "link): remove the link")
        wanted = stat.S_ISDIR if path.name in (LOGS_DIR, ".hydra") else stat.S_ISREG
        if not wanted(info.st_mode):
            return (f"{path} is {files.kind(info.st_mode)} where a run keeps its own "
                    f"{'folder' if wanted is stat.S_ISDIR else 'file'}: move it away")
    for name in (LOGS_DIR, ".hydra"):
        try:
            files.check_tree(folder / name)
        except (OSError, files.FileRefused) as err:
            return str(err)
    return None


def checkpoints(folder: Path) -> list[Path]:
    """The checkpoints in a folder: ``checkpoint.pt`` and those of a split population's parts
    (``checkpoint-<first seed>.pt``); a user's ``checkpoint-copy.pt`` is not one."""
    return sorted(p for p in Path(folder).glob("checkpoint*.pt") if p.is_file() and _is_run_file(p.name))


def state(folder: Path) -> FolderState:
    """The folder's state (see the module's docstring); reads only small files, never torch."""
    folder = Path(folder)
    link = linked_file(folder)
    if link:
        return FolderState("damaged", folder, problem=link)
    try:
        summary = read_summary(folder)
    except RunFolderError as err:
        return FolderState("damaged", folder, problem=str(err))
    if summary is not None:
        if summary["status"] not in FINAL_STATUSES:
            return FolderState("damaged", folder, problem=f"{folder / SUMMARY_FILE} records status "
                               f"{summary['status']!r}, not a finished run")
        problem = _unverifiable(summary) or _bad_values(folder, summary) or _mismatch(folder, summary)
        if problem is not None:
            return FolderState("damaged", folder, summary, problem)
        return FolderState("finished", folder, summary)
    if checkpoints(folder):
        return FolderState("resumable", folder)
    weights = [name for name in WEIGHT_FILES if (folder / name).exists()]
    if weights:
        return FolderState("damaged", folder, problem=f"it holds {' and '.join(weights)} but no {SUMMARY_FILE} "
                           "and no checkpoint (a finished run whose summary is lost?)")
    return FolderState("empty", folder)


LEGACY_FILE = Path(__file__).with_name("legacy_summaries.txt")
_legacy: dict[str, str] | None = None


def legacy_era(commit) -> str | None:
    """For a commit of the project from before summaries were sealed: "files" (its summaries record
    neither their files nor their own digest) or "digest" (they record their files, not their own
    digest); None for any other commit (``engine/legacy_summaries.txt``)."""
    global _legacy
    if _legacy is None:
        _legacy = {}
        for line in files.read_text(LEGACY_FILE, 1 << 20, "list of commits").splitlines():
            if line.strip() and not line.startswith("#"):
                full, era = line.split()
                _legacy[full] = era
    return _legacy.get(commit) if isinstance(commit, str) else None


def _unverifiable(summary: dict) -> str | None:
    """Why a summary cannot be checked (None: it can): one without its "files" record or its own
    digest counts as written by an earlier version only if its recorded commit is one of those
    versions; otherwise it was edited or damaged."""
    code = summary.get("code")
    commit = code.get("commit") if isinstance(code, dict) else None
    era = legacy_era(commit)
    if "files" not in summary and era != "files":
        return (f"{SUMMARY_FILE} records no \"files\" (the sizes and SHA-256 of its metrics and weights) and its "
                f"commit ({str(commit)[:12]}) is not one from before summaries recorded them: edited or damaged")
    if DIGEST_KEY not in summary and era is None:
        return (f"{SUMMARY_FILE} records no SHA-256 of its own content and its commit ({str(commit)[:12]}) is not one "
                "from before summaries recorded it: edited or damaged")
    return None


# No episode totals more: at most racing.config.MAX_STEPS steps, each rewarded at most the top speed
# or penalised a crash (a bound far above any, so that statistics over summaries cannot overflow)
FINAL_MEAN_BOUND = 1e12


def _bad_values(folder: Path, summary: dict) -> str | None:
    """What makes a summary's values unusable (None: nothing): a field of another type than train.py
    writes (a report sorts, groups and averages them), a final performance that is not a finite
    number within what an episode can total, a completed run without one."""
    import math

    number = (int, float)
    types = {"algo": str, "er": str, "seed": int, "episodes": int, "status": str, "final_window": (int, type(None)),
             "code": (dict, type(None)), "population": (dict, type(None)), "evaluation": (dict, type(None)),
             "numerics": (dict, type(None)), "compile": (dict, type(None)), "paths": (list, type(None)), "wall_time_s": (*number, type(None)),
             "cpu_time_s": (*number, type(None)), "resumed_at": (int, type(None)), "final_mean": (*number, type(None))}
    for key, kind in types.items():
        if key in summary and (isinstance(summary[key], bool) or not isinstance(summary[key], kind)):
            return f"{folder / SUMMARY_FILE} records {key} {json.dumps(summary[key])[:60]}, not what train.py writes there"
    final = summary.get("final_mean")
    if final is not None and not math.isfinite(final):
        return f"{folder / SUMMARY_FILE} records final_mean {final!r}, not a finite number"
    if final is not None and abs(final) > FINAL_MEAN_BOUND:
        return (f"{folder / SUMMARY_FILE} records final_mean {final:.3g}, beyond what any episode can total "
                f"(|{FINAL_MEAN_BOUND:.0e}|)")
    if final is None and summary.get("status") == "completed":
        return f"{folder / SUMMARY_FILE} records a completed run without a final performance"
    if summary["episodes"] < 0 or summary["seed"] < 0:
        return f"{folder / SUMMARY_FILE} records a negative episode count or seed"
    return None


def _mismatch(folder: Path, summary: dict) -> str | None:
    """What differs between the folder's files and those its summary stands for (None: nothing)."""
    recorded = summary.get("files")
    if isinstance(recorded, dict):
        for name, expected in recorded.items():
            path = folder / name
            if name in WEIGHT_FILES and not os.path.lexists(path):
                continue  # not kept (archives keep the actor, or nothing): whoever needs it says it is missing
            try:
                info = os.lstat(path)
            except OSError:
                return f"{path} is missing (its summary records it)"
            if not stat.S_ISREG(info.st_mode):
                return f"{path} is {files.kind(info.st_mode)}, not the file its summary records"
            size = info.st_size  # sizes first: a file grown to gigabytes is not read
            if size != expected.get("bytes"):
                return (f"{path} is not the file its summary records ({size} bytes where "
                        f"{expected.get('bytes')} were written)")
            if file_digest(path) != expected:
                return f"{path} differs from the file its summary records (its SHA-256)"
        return None
    weights = ("model.zip",) if str(summary["algo"]).startswith("sb3_") else WEIGHT_FILES  # baseline.py's
    for name in (METRICS_FILE, *weights):  # summaries from before the record: the metrics, and weights if kept
        path = folder / name
        if name != METRICS_FILE and not os.path.lexists(path):
            continue  # not kept (archives keep the actor, or nothing): whoever needs it says it is missing
        if not files.is_file(path) or path.stat().st_size == 0:
            return f"{path} is {'missing' if not os.path.lexists(path) else 'empty or not a regular file'}"
    return None


def clear(folder: Path) -> None:
    """Remove a run's files from ``folder``, the summary first (so the folder never shows an old
    summary beside a new run's files); other files are left alone."""
    folder = Path(folder)
    files.remove(folder / SUMMARY_FILE)
    for path in [folder / name for name in (METRICS_FILE, *WEIGHT_FILES)] + checkpoints(folder):
        files.remove(path)
    files.remove_tree(folder / LOGS_DIR)  # refused whole if anything in it is not a run's own file
    remove_temporaries(folder)


def remove_temporaries(folder: Path) -> None:
    """Temporary files a killed writer left behind (``door.files.write_atomic``'s
    ``<name>.<8 hex>.tmp``, or an older ``<name>.tmp``), for the files a run writes only: a user's own
    ``*.tmp`` stays."""
    for path in Path(folder).glob("*.tmp"):
        match = files.TEMPORARY.fullmatch(path.name)
        if match and _is_run_file(match["name"]) and (files.is_file(path) or path.is_symlink()):
            files.remove(path)


_held: dict[Path, list] = {}  # folder -> [file descriptor, depth]: a process may nest its own locks
_writing: list[str] = []  # the run folders this process writes (``lock``'s, from before they are made), as real paths


def written_here(path) -> Path | None:
    """The run folder this process is the writer of (it holds, or is taking, its ``lock``) that ``path`` lies in
    (None: none). A tool may write there, as its run's writer, and nowhere else inside a run folder."""
    real = os.path.realpath(path)
    for folder in _writing:
        if real == folder or real.startswith(folder.rstrip(os.sep) + os.sep):
            return Path(folder)
    return None


@contextlib.contextmanager
def lock(folders, root=None) -> None:
    """Hold the lock of every folder (created if missing) for the block; ``RunFolderBusy`` at once
    if another process holds one of them. Re-entrant within a process. Every folder from ``root``
    (default: each folder itself) down to each folder is checked first (``door.files.folder``):
    a member's folder that is a link to another folder is refused, never written through."""
    taken: list[Path] = []
    writing = [os.path.realpath(f) for f in folders]
    _writing.extend(writing)
    try:
        for folder in folders:
            try:
                files.folder(folder, root if root is not None else folder, create=True)
            except (OSError, files.FileRefused) as err:  # a path that cannot be a run folder: before anything runs
                raise RunFolderError(f"cannot use {folder} as a run folder ({err})") from None
        for folder in dict.fromkeys(Path(f).resolve() for f in folders):
            _acquire(folder)
            taken.append(folder)
        yield
    finally:
        for folder in reversed(taken):
            _release(folder)
        for folder in writing:
            _writing.remove(folder)


def _acquire(folder: Path) -> None:
    if folder in _held:
        _held[folder][1] += 1
        return
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock (the docs say so)
        _held[folder] = [None, 1]
        return
    path = folder / LOCK_FILE
    try:
        fd = files.open_in_place(path)  # never through a link, never a hard link to a file elsewhere
    except (OSError, files.FileRefused) as err:  # a path that cannot be a run folder: checked before anything runs
        raise RunFolderError(f"cannot use {folder} as a run folder ({err})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        busy = _busy(folder, fd)
        os.close(fd)
        raise RunFolderBusy(busy) from None
    except OSError as err:
        os.close(fd)
        raise RunFolderError(f"cannot lock {path} ({first_line(err)})") from None
    os.ftruncate(fd, 0)
    os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode())
    _held[folder] = [fd, 1]


def in_use(folder: Path) -> str | None:
    """Who holds ``folder``'s lock (None: nobody), found without writing anything: no lock file is
    made, none is truncated (the sweeper's check before any job starts)."""
    try:
        import fcntl
    except ImportError:
        return None
    try:
        fd = files.open_read(Path(folder) / LOCK_FILE)
    except (OSError, files.FileRefused):  # no lock file (nobody holds it), or not one: the run itself says so
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return None
    except BlockingIOError:
        return _busy(folder, fd)
    except OSError:
        return None
    finally:
        os.close(fd)  # releases a lock it took


def _busy(folder: Path, fd: int) -> str:
    """Why ``folder`` cannot be used now: another process holds the lock open on ``fd``."""
    return (f"{folder} is in use by another process ({_holder(fd)}); wait for it to end, or stop it (its run "
            "resumes from its checkpoint)")


def _holder(fd: int) -> str:
    try:
        text = os.pread(fd, 200, 0).decode(errors="replace").strip()
    except OSError:
        text = ""
    return text or "pid unknown"


def _release(folder: Path) -> None:
    entry = _held[folder]
    entry[1] -= 1
    if entry[1] == 0:
        del _held[folder]
        if entry[0] is not None:
            os.close(entry[0])  # closing the descriptor releases the flock


def files_read(paths) -> dict[str, str]:
    """{real path: what it is} of the files a tool reading ``paths`` reads: each path that is not a folder (an
    input file), and for a folder, the track file each run below it trained on (``env.track_file``; runs whose
    summary cannot be read are left to the tool's own reading)."""
    from engine.outputs import RunFolderError, read_summary

    found = {}
    for path in paths:
        if not os.path.isdir(path):
            found[os.path.realpath(path)] = "an input file"
            continue
        for summary in files.find(path, "summary.json"):
            try:
                settings = (read_summary(summary.parent) or {}).get("settings") or {}
            except RunFolderError:
                continue
            track_file = (settings.get("env") or {}).get("track_file") if isinstance(settings, dict) else None
            if isinstance(track_file, str) and track_file:
                found.setdefault(os.path.realpath(track_file), f"the track file of the run {summary.parent}")
    return found


def runs_numerics(runs: list[Path], choose: str | None = None) -> str:
    """The numerics mode the finished runs were trained in (runs from before the modes: native;
    damaged runs are skipped later, with their reason). ``choose``: the tool's option that picks a mode
    (named when the runs differ), if it has one."""
    from engine import numerics

    found = [state(run) for run in runs]
    modes = {((f.summary.get("settings") or {}).get("numerics", "native")) for f in found if f.kind == "finished"}
    if not modes:
        return numerics.DEFAULT
    if len(modes) > 1:
        raise RunFolderError(f"the runs were trained under different numerics ({sorted(modes)}); "
                             + (f"choose one with {choose}" if choose else "give runs of one numerics mode at a time"))
    return modes.pop()
