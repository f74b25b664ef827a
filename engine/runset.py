"""The run-set reader: which folders a tool's command line names as runs, each run once (torch-free).

Every tool that reads runs (report.py, evaluate.py, the leaderboard, the analyses, the search) asks
``read_runs`` and nothing else, so that one question has one answer everywhere:

- a *run* is a folder holding ``summary.json`` (``unfinished=True``: or ``metrics.csv``, a run killed or
  still running, which report.py lists as partial); a path names itself if it is one, else every run at
  any depth below it (``door.files.walk``: no recursion, links never entered);
- the same folder named twice, or reached through a link, is one run, under the name first given;
- two folders holding *one run* (the same recorded algorithm, replay mode, seed and settings: a copy of a
  folder, a backup beside it, the same run made twice) are one run: the first in order is read (the first
  intact one, if the first is damaged), the others are named in one line each and not counted (a copy would
  otherwise count as a second sample);
- a path with ``..`` is read as the system resolves it (after a link, ``..`` is not the folder its text names);
- a folder that cannot be listed is named in one line and skipped.

``RunSet.notes`` holds those lines; ``read_runs(..., say=name)`` prints them, prefixed with the tool's
name, to standard error. A path that is not a folder, or names no run, is a ``RunFolderError``.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

from door import files
from engine.outputs import METRICS_FILE, SUMMARY_FILE, RunFolderError, read_summary


@dataclass
class RunSet:
    runs: list[Path]  # each run once, in the order found (paths sorted within each named folder)
    notes: list[str] = field(default_factory=list)  # one line each: a repeat counted once, a folder skipped

    def __iter__(self):
        return iter(self.runs)

    def __len__(self) -> int:
        return len(self.runs)


def identity(folder: Path) -> str | None:
    """What the run in ``folder`` is, as it recorded it (its summary's algo, er, seed and settings), as a
    digest: two folders with one identity hold one run. None: no summary to read, or one that records no
    settings (a partial or damaged run, or one whose settings are unknown, is only ever the same run as itself)."""
    try:
        summary = read_summary(folder)
    except RunFolderError:
        return None
    if not summary or not isinstance(summary.get("settings"), dict) or not summary["settings"]:
        return None
    record = {key: summary.get(key) for key in ("algo", "er", "seed")} | {"settings": summary.get("settings")}
    return hashlib.sha256(json.dumps(record, sort_keys=True, default=str).encode()).hexdigest()


def _folders(path: Path, unfinished: bool, skip_named: str | None, notes: list[str]) -> list[Path]:
    marks = (SUMMARY_FILE, METRICS_FILE) if unfinished else (SUMMARY_FILE,)
    if any(os.path.lexists(path / mark) for mark in marks):
        return [path]
    found = []

    def unreadable(err: OSError) -> None:
        notes.append(f"skipped {err.filename}: it cannot be listed ({err.strerror or err})")

    for here, folders, names in files.walk(path, onerror=unreadable):
        if skip_named is not None and skip_named in folders:
            folders.remove(skip_named)  # a tool's own output folder (report.py's report/)
        if any(mark in names for mark in marks):
            found.append(Path(here))
    return found


def read_runs(paths, *, unfinished: bool = False, skip_named: str | None = None, say: str | None = None,
              copies: bool = True) -> RunSet:
    """The runs ``paths`` name (see the module's docstring). ``skip_named``: a folder name never entered
    (a tool's own outputs inside a sweep). ``say``: print the notes, prefixed with this tool name.
    ``copies=False``: folders are told apart by path only (the same run made twice counts twice: for the
    tools that check each folder, not count runs)."""
    runs: list[Path] = []
    notes: list[str] = []
    seen_paths: dict[str, Path] = {}
    seen_runs: dict[str, Path] = {}

    def say_notes() -> None:
        for note in notes if say else ():
            print(f"{say}: {note}", file=sys.stderr)

    for path in map(Path, paths):
        if ".." in path.parts:  # read as the system resolves it (a link before "..": not the folder the text names)
            path = Path(os.path.realpath(path))
        if not path.is_dir():
            say_notes()
            raise RunFolderError(f"{path} is not a folder; give a run's folder or a sweep's")
        found = _folders(path, unfinished, skip_named, notes)
        if not found:
            say_notes()
            raise RunFolderError(f"{path} holds no {'' if unfinished else 'finished '}train.py run (no "
                                 f"{SUMMARY_FILE}{'' if not unfinished else ' or ' + METRICS_FILE} in it or below it)")
        for folder in found:
            real = os.path.realpath(folder)
            if real in seen_paths:
                if str(seen_paths[real]) != str(folder):
                    notes.append(f"{folder} is {seen_paths[real]} (a link, or named twice): counted once")
                continue
            seen_paths[real] = folder
            key = identity(folder) if copies else None
            if key is not None and key in seen_runs:
                kept = seen_runs[key]
                if _intact(folder) and not _intact(kept):  # the intact one of the two stands for the run
                    runs[runs.index(kept)] = seen_runs[key] = folder
                    folder, kept = kept, folder
                notes.append(f"{folder} holds the same run as {kept} (the same recorded algorithm, replay "
                             "mode, seed and settings: a copy, or the run made twice): counted once")
                continue
            if key is not None:
                seen_runs[key] = folder
            runs.append(folder)
    say_notes()
    return RunSet(runs, notes)


def _intact(folder: Path) -> bool:
    """Whether ``folder`` holds a finished run whose files are as its summary records (``engine.rundir.state``)."""
    from engine.rundir import state

    return state(folder).kind == "finished"
