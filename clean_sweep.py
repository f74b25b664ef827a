"""Run a sweep from a clean export of one commit: ``python clean_sweep.py +experiment=paper_grid``.

Results you publish should come from one program. A sweep run from the working tree imports
whatever the tree holds when each job starts, so editing (or checking out) files during a long
sweep silently mixes code versions. This script exports a commit with ``git archive`` (HEAD
unless ``--commit``) into ``outputs/code/<commit>/`` and runs ``train.py -m`` from there with
the given Hydra overrides, into ``outputs/sweeps/<experiment>-<commit>/`` unless
``hydra.sweep.dir=...`` is given. The working tree can change freely meanwhile. Every run
records the export's commit in its ``summary.json`` (``code.origin: export``), and
``report.py`` refuses folders that mix versions.

Running the same command again resumes the sweep (finished runs are skipped, killed ones
resume from their checkpoints). The export uses this Python environment's packages, so
install the commit's own pins first if its ``pyproject.toml`` differs from the installed one.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

from door import files

ROOT = Path(__file__).resolve().parent


class SweepError(RuntimeError):
    """A commit or folder that cannot be used."""


def git(*args: str, binary: bool = False):
    result = subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=not binary)
    if result.returncode != 0:
        err = result.stderr if not binary else result.stderr.decode(errors="replace")
        raise SweepError(f"git {' '.join(args)} failed: {err.strip()}")
    return result.stdout


def resolve_commit(ref: str) -> str:
    if not (ROOT / ".git").exists():
        raise SweepError(f"{ROOT} is not a git work tree; clean_sweep.py exports commits from a clone")
    return git("rev-parse", "--verify", "--quiet", f"{ref}^{{commit}}").strip()


# where an export records its commit (``export-subst``): engine/COMMIT, experiment/COMMIT in
# commits made before the engine had its own package (they can still be exported and rerun)
COMMIT_FILES = (Path("engine") / "COMMIT", Path("experiment") / "COMMIT")


def exported_commit(code_dir: Path) -> str | None:
    """The commit an export's COMMIT file names, or None if ``code_dir`` holds none."""
    for name in COMMIT_FILES:
        if files.is_file(code_dir / name):
            return files.read_text(code_dir / name, 1024, "commit file").strip()
    return None


def export(commit: str, code_dir: Path) -> Path:
    """``git archive`` of ``commit`` unpacked into ``code_dir`` (kept if it is already there)."""
    existing = exported_commit(code_dir)
    if existing is not None:
        if existing != commit:
            raise SweepError(f"{code_dir} holds an export of another commit; remove it or choose --code-dir")
        differences = export_differences(git("archive", "--format=tar", commit, binary=True), code_dir)
        if differences:
            raise SweepError(f"{code_dir} is not the commit's export as it was made ({'; '.join(differences[:3])}"
                             f"{'; ...' if len(differences) > 3 else ''}): its code would run under the commit's "
                             "name; remove the folder (it is exported again) or choose --code-dir")
        for cache in sorted({p.parent for p in files.tree(code_dir) if p.parent.name == "__pycache__"}):
            files.remove_tree(cache)  # compiled bytecode is not checked: Python makes it afresh from the sources
        return code_dir
    if code_dir.exists():
        raise SweepError(f"{code_dir} exists but is not an export; remove it or choose --code-dir")
    archive = git("archive", "--format=tar", commit, binary=True)
    # unpacked into a folder of this process's own, so that sweeps started together can export
    # the same commit at once: the first rename wins and the others drop their copy
    files.folder(code_dir.parent, code_dir.parent, create=True)
    partial = files.private_folder(code_dir.parent, code_dir.name + ".partial-")
    try:
        files.extract_tar(archive, partial)
        if exported_commit(partial) != commit:
            raise SweepError("the export's COMMIT file was not filled in; is .gitattributes in the commit?")
        try:
            files.rename_folder(partial, code_dir)
        except FileExistsError:  # another sweep's export of the same commit landed first
            if exported_commit(code_dir) is None:
                raise
    finally:
        if partial.exists():
            files.remove_tree(partial)
    return code_dir


def export_differences(archive: bytes, code_dir: Path) -> list[str]:
    """How the folder ``code_dir`` differs from the tar ``archive`` of a commit (empty: it does not):
    files changed, missing or added (``__pycache__`` folders aside, which are removed before a run)."""
    import io
    import tarfile

    expected = {}
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        for member in tar.getmembers():
            if member.isfile():
                expected[member.name] = tar.extractfile(member).read()
    found = {p.relative_to(code_dir).as_posix() for p in files.tree(code_dir) if "__pycache__" not in p.parts}
    differences = [f"{name} was added" for name in sorted(found - set(expected))]
    for name, data in sorted(expected.items()):
        if name not in found:
            differences.append(f"{name} is missing")
        else:
            try:
                same = files.read(code_dir / name, len(data), "file of the export") == data
            except (OSError, files.FileRefused):
                same = False
            if not same:
                differences.append(f"{name} was changed")
    return differences


def sweep_dir_of(overrides: list[str], commit: str) -> tuple[Path, list[str]]:
    """The sweep folder (absolute: the sweep runs from the export) and the other overrides."""
    rest, given = [], None
    for item in overrides:
        if item.startswith("hydra.sweep.dir="):
            given = Path(item.split("=", 1)[1])
        else:
            rest.append(item)
    if given is None:
        names = [o.split("=", 1)[1] for o in rest if o.startswith("+experiment=")]
        given = Path("outputs") / "sweeps" / f"{names[0] if names else 'sweep'}-{commit[:12]}"
    return given.resolve(), rest


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--commit", default="HEAD", help="the commit to run (default: HEAD)")
    parser.add_argument("--code-dir", type=Path, help="where to export it (default: outputs/code/<commit>)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of the sweep, e.g. +experiment=paper_grid")
    args = parser.parse_args(argv)
    try:
        commit = resolve_commit(args.commit)
        code_dir = export(commit, (args.code_dir or ROOT / "outputs" / "code" / commit[:12]).resolve())
        sweep_dir, overrides = sweep_dir_of(args.overrides, commit)
    except SweepError as err:
        print(f"clean_sweep: {err}", file=sys.stderr)
        return 2
    if git("status", "--porcelain", "--untracked-files=no").strip():
        print("clean_sweep: note: the working tree has uncommitted changes; they are not in the export",
              file=sys.stderr)
    print(f"clean_sweep: commit {commit} exported to {code_dir}; runs go to {sweep_dir}", file=sys.stderr)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(code_dir), os.environ.get("PYTHONPATH")]))}
    command = [sys.executable, str(code_dir / "train.py"), "-m", *overrides, f"hydra.sweep.dir={sweep_dir}"]
    code = subprocess.run(command, cwd=code_dir, env=env).returncode
    if code == 0:
        print(f"clean_sweep: done; report with: python report.py {sweep_dir}", file=sys.stderr)
    return code


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("clean_sweep", main))
