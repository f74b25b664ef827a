"""The output writer: where a tool may write, decided once for every tool (torch-free).

A tool's outputs (tables, pages, figures, weights, a baseline's run folders) never go

- inside or over a run folder (``engine.rundir.run_folder_of``: a folder with a run's marks, finished,
  training or damaged, a population's top folder included, or below one): those hold only their run's own
  files, and an output there would replace one of them or damage the run; the one exception is a run
  folder the tool itself writes as that run's writer (it holds the run's lock: ``baseline.py``), which must
  not lie inside another run's folder;
- over a file the tool reads (its input tables, a run's track file, anything it read through the door).

It is decided twice, with one answer (``output_problem``): before the work, on the paths the command line
names (``check_outputs``, ``check_output_folder``: ``parser.error`` in one line), and at every write, append,
new folder or deletion the tool makes (``guard``, set by ``engine.processes.run_tool`` for every tool and by
``engine.pool`` in its workers: ``door.files.FileRefused`` in one line). The door's writes replace a link at
the file's name, never write through it (``door.files.write_atomic``).
"""

from __future__ import annotations

import os
from pathlib import Path

from door import files


def output_problem(path, replaces: bool = True) -> str | None:
    """Why a tool may not write ``path`` (None: it may). ``replaces``: its content is replaced or appended to (a
    file the tool read may not be); else it is made or deleted."""
    from engine.rundir import run_folder_of, written_here

    given = os.fspath(path)
    path = Path(os.path.abspath(given))
    # where the system writes it: the folder resolved (a link before ".." is not the folder the text names), the
    # name itself not (a link there is replaced, never followed)
    real = Path(os.path.realpath(os.path.dirname(given) or ".")) / os.path.basename(given)
    if real != path:
        problem = output_problem(real, replaces)
        if problem is not None:
            return problem
    own = written_here(path)
    if own is not None:  # a run this process writes: its own files, if the run is not inside another run
        outer = run_folder_of(own.parent)
        return None if outer is None else (f"{own} is inside the run folder {outer}, which holds only its run's own "
                                           "files; write the runs elsewhere")
    folder = run_folder_of(path)
    if folder is not None:
        where = "the run folder" if folder == path else "inside the run folder"
        return f"{path} is {where} {folder}, which holds only the run's own files; write the output elsewhere"
    if replaces and files.was_read(path):
        return f"{path} is a file this command reads; write the output elsewhere"
    return None


def guard() -> None:
    """Every write this process makes from now on asks ``output_problem`` first (a tool's process)."""
    files.guard_writes(output_problem)


def check_outputs(parser, reads=(), **outputs) -> None:
    """Before a tool's work: each output file its command line names (``table=args.table``, ...) can
    be written (``door.files.check_target``), may be written by a tool (``output_problem``), and is none
    of the files the tool reads (``reads``: its input paths; for a folder, the track file of every run in it,
    ``engine.rundir.files_read``), else ``parser.error`` with one line."""
    from engine.rundir import files_read

    inputs = files_read(reads) if reads else {}
    for real, what in list(inputs.items()):  # another name of an input (a hard link) is the input too
        try:
            info = os.stat(real)
            inputs[(info.st_dev, info.st_ino)] = what
        except OSError:
            pass
    for option, path in outputs.items():
        if path is None:
            continue
        name = f"--{option.replace('_', '-')}"
        read = inputs.get(os.path.realpath(path))
        try:
            info = os.stat(path)
            read = read or inputs.get((info.st_dev, info.st_ino))
        except OSError:
            pass
        if read is not None:
            parser.error(f"{name} {path} is {read}, which this command reads; write the output elsewhere")
        if os.path.isdir(path):
            parser.error(f"{name} {path} is a folder; give a file name")
        problem = output_problem(path)
        if problem is not None:
            parser.error(f"{name}: {problem}")
        try:
            files.check_target(path)
        except files.FileRefused as err:
            parser.error(f"{name}: {err}")


def check_output_folder(parser, option: str, path) -> None:
    """Before a tool's work: the folder its ``option`` names for its outputs is not a run's folder nor
    inside one (``output_problem``), and not a file; else ``parser.error`` with one line."""
    if os.path.lexists(path) and not os.path.isdir(path):
        parser.error(f"{option} {path} is not a folder; give the folder the outputs go to")
    problem = output_problem(path, replaces=False)
    if problem is not None:
        parser.error(f"{option}: {problem}")
