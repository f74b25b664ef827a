"""Which code made a run: the git commit, whether the source differed from it, and a hash of
the source itself. Every run records it in ``summary.json``; ``report.py`` refuses to mix runs
of different code.

The source hash covers everything that decides what a run computes: the packages
(``racing``, ``losses``, ``collectors``, ``learners``, ``engine``, ``analysis``), ``conf/`` and ``train.py``. Two runs
with the same source hash ran the same code, whatever the commit says; a README change makes
a new commit but not a new source hash.

The commit comes from git when the project is a git work tree, and otherwise from
``engine/COMMIT``, which ``git archive`` fills in (``export-subst`` in ``.gitattributes``),
so a clean export (``clean_sweep.py``) knows its commit without a ``.git`` folder.
"""

from __future__ import annotations

import functools
import hashlib
import subprocess
from pathlib import Path

from door import files as door

ROOT = Path(__file__).resolve().parent.parent
SOURCE_PATHS = ("door", "racing", "losses", "collectors", "learners", "engine", "analysis", "conf", "train.py")
SOURCE_SUFFIXES = (".py", ".yaml", ".csv", ".cpp", ".h")  # the C++ kernels compute every product under fma
COMMIT_FILE = Path(__file__).resolve().parent / "COMMIT"


def source_files(root: Path = ROOT) -> list[Path]:
    files = []
    for name in SOURCE_PATHS:
        path = root / name
        if path.is_file():
            files.append(path)
        elif path.is_dir():
            files += [p for p in door.tree(path) if p.suffix in SOURCE_SUFFIXES and "__pycache__" not in p.parts]
    return sorted(files)


def source_hash(root: Path = ROOT) -> str:
    """SHA-256 (first 16 hex digits) over the source files' relative paths and contents."""
    digest = hashlib.sha256()
    for path in source_files(root):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0")
        digest.update(door.read(path, 1 << 26, "source file") + b"\0")
    return digest.hexdigest()[:16]


def _git(root: Path, *args: str) -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def _git_version(root: Path) -> dict | None:
    """Commit and dirty flag if ``root`` is the top of a git work tree (not a folder inside one)."""
    top = _git(root, "rev-parse", "--show-toplevel")
    if top is None or Path(top).resolve() != root.resolve():
        return None
    commit = _git(root, "rev-parse", "HEAD")
    status = _git(root, "status", "--porcelain", "--untracked-files=normal", "--", *SOURCE_PATHS)
    if commit is None or status is None:
        return None
    return {"commit": commit, "dirty": bool(status), "origin": "git"}


def _export_version() -> dict | None:
    try:
        commit = door.read_text(COMMIT_FILE, 1024, "commit file").strip()
    except (OSError, ValueError):
        return None
    if len(commit) == 40 and all(c in "0123456789abcdef" for c in commit):
        # An export holds exactly the commit's files; a later edit shows in the source hash only.
        return {"commit": commit, "dirty": None, "origin": "export"}
    return None


@functools.lru_cache(maxsize=1)
def code_version() -> dict:
    """``{"commit", "dirty", "origin", "source"}`` of the code running now.

    ``origin`` is ``git`` (a work tree: ``dirty`` says whether the source differs from the
    commit), ``export`` (a ``git archive`` export: ``dirty`` is unknown, ``None``) or
    ``unknown`` (neither: ``commit`` is ``None``). ``source`` is ``source_hash()``.
    """
    version = _git_version(ROOT) or _export_version() or {"commit": None, "dirty": None, "origin": "unknown"}
    return {**version, "source": source_hash(ROOT)}


def software_versions() -> dict:
    """Versions of Python and of the libraries whose arithmetic a run depends on."""
    import platform

    import numpy
    import torch
    import torchrl

    return {"python": platform.python_version(), "torch": torch.__version__, "numpy": numpy.__version__,
            "torchrl": torchrl.__version__, "cpu": torch.backends.cpu.get_cpu_capability()}


def describe(version: dict | None) -> str:
    """One line: ``commit 1a2b3c4d5e6f (clean), source 0123abcd...``."""
    if not version:
        return "code version not recorded"
    commit = version.get("commit")
    dirty = version.get("dirty")
    state = {True: "with uncommitted changes", False: "clean", None: version.get("origin", "unknown")}[dirty]
    text = (f"commit {commit[:12]} ({state})" if commit else "no commit") + f", source {version.get('source')}"
    if version.get("resumed_from"):
        text += f", resumed from a checkpoint of source {version['resumed_from'].get('source')}"
    return text
