"""The one door: every file the project reads, writes, replaces or deletes goes through this module
(torch-free; ``tests/test_one_door.py`` checks that no other module opens, replaces or deletes a file).

Its rules, each tested once here for every caller (``tests/test_files.py``):

1. **Regular files only, checked on the opened descriptor.** Every open adds ``O_NOFOLLOW``,
   ``O_NONBLOCK`` and ``O_CLOEXEC``, then ``fstat``s what it opened: a FIFO, a device, a socket or a
   folder is refused at once (nothing blocks on it), never by its name first. A symbolic link at the
   file's own name is refused, except for a file a user names as input (``follow=True``: a track
   file, a model to score), where the link is followed and its target must still be a regular file.
2. **A file written in place has one link.** A lock or a file appended to is refused if it has
   another name (a hard link to a file elsewhere is never truncated or appended to). Replacing
   writes make a new file, so the other name keeps its old content.
3. **Folders on the way are folders.** ``folder(path, root)`` checks (and may create) every folder
   from ``root`` down to ``path``: each a real folder, none a link. A run checks its members'
   folders, ``logs/`` and ``.hydra/`` this way before writing into them; ``check_tree`` checks a
   folder whole (no link, special file or hard link at any depth) before a writer that opens its
   own files (TorchRL's loggers) writes into it.
4. **Reads are bounded.** Every read names the most bytes the file can hold; a larger file is
   refused unread (``stream`` reads any size in pieces, in little memory).
5. **Writes are atomic.** ``write_atomic`` writes a temporary of its own (created exclusively,
   ``<name>.<8 hex>.tmp``) beside the file, flushes it to the disk and renames it over the file,
   which must be absent, a regular file or a link (never a folder or a special file); a crash at any
   byte leaves the old file or the new one.
6. **Deletions remove what is named.** ``remove`` deletes one named file or link (the link itself,
   never its target), never a folder; ``remove_tree`` deletes a folder after ``check_tree``.
7. **Names are names.** A configuration value that becomes a path component goes through ``name``:
   no separator, not ``.`` or ``..``, no NUL, at most 255 bytes.
8. **Code is loaded only as recorded.** ``load_library`` loads a shared library through the very
   descriptor whose bytes matched the SHA-256 recorded when it was built; a folder whose files
   another program loads as code (TorchInductor's cache) is ``private``: this user's, not a link,
   mode 0700.
9. **A tool writes only where its outputs may go.** A command that is a tool (not a run's writer) sets a
   guard (``guard_writes``, set by ``engine.processes.run_tool`` for every tool) that every write,
   append, new folder and deletion asks first; while it is set, the files read are remembered
   (``was_read``) so that the guard can refuse an output over one of them.

Every refusal is ``FileRefused`` (a ``ValueError``), one sentence naming the path and the reason;
a full disk is ``DiskFull``; a missing file stays ``FileNotFoundError``; any other error of the
system (permissions, a read-only disk, a name too long) becomes a ``FileRefused`` naming it.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import re
import secrets
import shutil
import stat
from pathlib import Path

_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_NONBLOCK = getattr(os, "O_NONBLOCK", 0)
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)
_DIRECTORY = getattr(os, "O_DIRECTORY", 0)
NAME_BYTES = 255
TEMPORARY = re.compile(r"(?P<name>.+?)\.(?:[0-9a-f]{8}\.)?tmp")  # write_atomic's temporaries (and older <name>.tmp)


class FileRefused(ValueError):
    """A file or folder the door will not read or write; the message names it and says why."""


class DiskFull(FileRefused):
    """A file could not be written for want of space; the previous version of it (if any) is intact."""

    def __init__(self, path, needed: int, quota: bool = False):
        self.path, self.needed = Path(path), needed
        free, entries = free_bytes(self.path.parent), free_entries(self.path.parent)
        if quota:  # EDQUOT: this user's share, whatever the device holds
            ran_out, remedy = "this user's disk quota is used up", "free some of your files"
        elif entries == 0:  # bytes to spare, but no file entry (inode) left for a new file
            ran_out, remedy = (f"the device of {self.path} has no file entries (inodes) left"
                               f"{'' if free is None else f' (though {free:,} bytes are free)'}",
                               "delete some files (many small ones free the most)")
        else:
            have = "" if free is None else f", {free:,} are free"
            what = f"writing it needs {needed:,} bytes{have}" if needed else f"it could not be flushed to the disk{have}"
            ran_out, remedy = f"no space left on the device of {self.path}: {what}", "free some space"
        super().__init__(f"{ran_out}; the folder keeps its last good files ({remedy} and run the same command again)")


def free_bytes(folder) -> int | None:
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def free_entries(folder) -> int | None:
    """File entries (inodes) an unprivileged user may still make on ``folder``'s device (None: unknown; some file
    systems report 0 for both totals, having no fixed count)."""
    try:
        info = os.statvfs(folder)
    except (OSError, AttributeError):
        return None
    return None if info.f_files == 0 else info.f_favail


def kind(mode: int) -> str:
    """What a file is, in words, from its ``st_mode``."""
    for test, words in ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                        (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                        (stat.S_ISSOCK, "a socket"), (stat.S_ISLNK, "a symbolic link"), (stat.S_ISREG, "a file")):
        if test(mode):
            return words
    return "a special file"


def _refusal(path, err: OSError, verb: str, follow: bool = False) -> Exception:
    """The error to raise for ``err`` while doing ``verb`` to ``path``: missing files stay
    ``FileNotFoundError``, a full disk is ``DiskFull``, anything else a ``FileRefused`` sentence."""
    if isinstance(err, FileNotFoundError):
        return err
    if err.errno in (errno.ENOSPC, errno.EDQUOT):
        return DiskFull(path, 0, quota=err.errno == errno.EDQUOT)
    reason = {errno.ELOOP: "its symbolic links loop" if follow else "it is a symbolic link (a file here is never read "
                                                                       "or written through a link): remove the link",
              errno.ENXIO: "it is a FIFO or a device, not a regular file",
              errno.EISDIR: "it is a folder, not a file",
              errno.ENAMETOOLONG: "the path is too long for the file system",
              errno.EROFS: "the file system is read-only",
              errno.EACCES: "permission denied", errno.EPERM: "the operation is not permitted",
              errno.ENOTDIR: "a part of the path is not a folder",
              errno.EEXIST: "something else is already there"}.get(err.errno, err.strerror or str(err))
    return FileRefused(f"cannot {verb} {path}: {reason}")


_guard = None  # rule 9: callable(path, replaces: bool) -> why this process may not write there, or None
_read: set = set()  # the real paths and (device, inode) of the files read while a guard is set


def guard_writes(check) -> None:
    """Rule 9: from now on every write, append, new folder or deletion asks ``check(path, replaces)`` (``replaces``:
    the path's content is replaced or appended to, not deleted or made) and is refused with its answer if it gives
    one; ``None`` lifts the guard."""
    global _guard
    _guard = check
    _read.clear()


def guarded() -> bool:
    """Whether a guard is set (a tool's process)."""
    return _guard is not None


def was_read(path) -> bool:
    """Whether the file at ``path`` (by its real path, or as another name of the same file: a hard link) was read
    by this process while a guard was set."""
    if os.path.realpath(path) in _read:
        return True
    try:
        info = os.stat(path)
    except OSError:
        return False
    return (info.st_dev, info.st_ino) in _read


def _ask(path, replaces: bool = True) -> None:
    if _guard is not None:
        problem = _guard(Path(path), replaces)
        if problem:
            raise FileRefused(problem)


def _open(path, flags: int, verb: str, follow: bool = False, single_link: bool = False, mode: int = 0o644):
    """``(fd, stat)`` of a regular file opened with the door's flags (rule 1, and rule 2 if ``single_link``)."""
    if flags & (os.O_WRONLY | os.O_RDWR | os.O_APPEND | os.O_CREAT):
        _ask(path)
    elif _guard is not None:
        _read.add(os.path.realpath(path))
        try:
            info = os.stat(path)
            _read.add((info.st_dev, info.st_ino))
        except OSError:
            pass
    try:
        fd = os.open(path, flags | _NONBLOCK | _CLOEXEC | (0 if follow else _NOFOLLOW), mode)
    except OSError as err:
        raise _refusal(path, err, verb, follow) from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise FileRefused(f"cannot {verb} {path}: it is {kind(info.st_mode)}, not a regular file")
        if single_link and info.st_nlink > 1:
            raise FileRefused(f"cannot {verb} {path}: it has {info.st_nlink} names (a hard link); a file written in "
                              "place must have one, so that nothing elsewhere is changed: remove it")
    except BaseException:
        os.close(fd)
        raise
    return fd, info


# ---------------------------------------------------------------------------------------------- reading

def _a(what: str) -> str:
    return f"{'an' if what[:1].lower() in 'aeiou' else 'a'} {what}"


def read(path, limit: int, what: str = "file", follow: bool = False) -> bytes:
    """The bytes of the regular file at ``path``, refused unread if larger than ``limit`` bytes."""
    fd, info = _open(path, os.O_RDONLY, "read", follow)
    with os.fdopen(fd, "rb") as f:
        if info.st_size > limit:
            raise FileRefused(f"{path} is {info.st_size:,} bytes, more than {_a(what)} holds (at most {limit:,}): "
                              f"damaged, or not {_a(what)}; it was not read")
        chunks, total = [], 0
        try:  # in pieces: one read of the limit would reserve the whole limit at once (fails under ulimit -v)
            while total <= limit and (chunk := f.read(min(1 << 20, limit + 1 - total))):
                chunks.append(chunk)
                total += len(chunk)
        except OSError as err:
            raise _refusal(path, err, "read") from None
        data = b"".join(chunks)
    if len(data) > limit:  # grew while read, or a file whose size the system does not report (/proc)
        raise FileRefused(f"{path} holds more than {limit:,} bytes, more than {_a(what)} holds: not read further")
    return data


def read_text(path, limit: int, what: str = "file", follow: bool = False) -> str:
    """``read`` as UTF-8 text; a file that is not text is refused."""
    data = read(path, limit, what, follow)
    try:
        return data.decode()
    except UnicodeDecodeError as err:
        raise FileRefused(f"{path} is not text (UTF-8): byte {err.start} cannot be read; not a {what}") from None


def read_csv(path, limit: int, what: str = "table", follow: bool = True, comments: bool = True) -> list[dict]:
    """The rows of a CSV table (``read_text``'s rules; a UTF-8 byte-order mark is read past; with ``comments``,
    lines starting with '#' are comments). A table whose header names a column twice, a row with more fields
    than the header, or a field beyond the csv module's limit is refused (``FileRefused``), not read as
    something else."""
    import csv
    import io

    text = read_text(path, limit, what, follow).removeprefix("\ufeff")
    lines = (line for line in io.StringIO(text, newline="") if not (comments and line.startswith("#")))
    try:
        reader = csv.DictReader(lines)
        header = reader.fieldnames or []
        repeated = sorted({name for name in header if header.count(name) > 1})
        if repeated:
            raise FileRefused(f"{path}'s header names column {repeated[0]!r} twice: not a {what}")
        rows = []
        for row in reader:
            if None in row:
                raise FileRefused(f"{path} line {reader.line_num} has more fields than its header: not a {what}")
            rows.append(row)
    except csv.Error as err:
        raise FileRefused(f"{path} is not a CSV table ({err}): not a {what}") from None
    return rows


@contextlib.contextmanager
def stream(path, follow: bool = False):
    """A binary file object of the regular file at ``path`` (for reading a file of any size in pieces)."""
    fd, _ = _open(path, os.O_RDONLY, "read", follow)
    with os.fdopen(fd, "rb") as f:
        yield f


def digest(path, follow: bool = False) -> dict:
    """``{"bytes", "sha256"}`` of a regular file, read in pieces."""
    sha, size = hashlib.sha256(), 0
    with stream(path, follow) as f:
        while chunk := f.read(1 << 20):
            sha.update(chunk)
            size += len(chunk)
    return {"bytes": size, "sha256": sha.hexdigest()}


def is_file(path) -> bool:
    """Whether ``path`` is a regular file itself (not a link to one), by ``lstat``."""
    try:
        return stat.S_ISREG(os.lstat(path).st_mode)
    except OSError:
        return False


def is_folder(path) -> bool:
    """Whether ``path`` is a folder itself (not a link to one), by ``lstat``."""
    try:
        return stat.S_ISDIR(os.lstat(path).st_mode)
    except OSError:
        return False


def walk(top, topdown: bool = True, onerror=None):
    """``os.walk(top, followlinks=False)`` without recursion: (folder, its folders, its other names) for
    every folder at or below ``top``, sorted, at any depth (``os.walk`` of Python 3.11 recurses and a chain of
    1,500 folders ends it in a ``RecursionError``). A link is listed, never entered (a loop cannot hang it).
    A folder that cannot be listed is passed to ``onerror`` (an ``OSError``) and skipped. ``topdown``: a
    folder before those below it (its folder list may be pruned in place); else after them. The one walk
    of the project: every walk over a user's folders is this one."""
    stack: list = [(os.fspath(top), False)]
    while stack:
        here, done = stack.pop()
        if done:
            yield here[0], here[1], here[2]
            continue
        try:
            with os.scandir(here) as entries:
                folders, names = [], []
                for entry in entries:
                    try:
                        is_dir = entry.is_dir(follow_symlinks=False)
                    except OSError:
                        is_dir = False
                    (folders if is_dir else names).append(entry.name)
        except OSError as err:
            if onerror is not None:
                onerror(err)
            continue
        folders.sort()
        names.sort()
        if topdown:
            yield here, folders, names
            stack.extend((os.path.join(here, name), False) for name in reversed(folders))
        else:
            stack.append(((here, folders, names), True))
            stack.extend((os.path.join(here, name), False) for name in reversed(folders))


def tree(root) -> list[Path]:
    """Every regular file at or below the folder ``root`` (sorted), links never followed."""
    found = []
    for folder, folders, names in walk(root):
        found += [Path(folder) / entry for entry in names if is_file(Path(folder) / entry)]
    return sorted(found)


def find(root, name: str, onerror=None) -> list[Path]:
    """Every file called ``name`` at or below the folder ``root`` (sorted), links never followed
    (a link loop cannot hang it), at any depth (``walk``)."""
    found = []
    for folder, folders, names in walk(root, onerror=onerror):
        if name in names:
            found.append(Path(folder) / name)
    return sorted(found)


# ---------------------------------------------------------------------------------------------- folders

def name(value, what: str) -> str:
    """``value`` as one path component (rule 7); ``FileRefused`` saying what was expected otherwise."""
    text = str(value)
    if (not text or text in (".", "..") or "/" in text or "\0" in text or (os.altsep and os.altsep in text)
            or len(text.encode(errors="surrogateescape")) > NAME_BYTES):
        raise FileRefused(f"{what} must be a name (no '/', not '.' or '..', at most {NAME_BYTES} bytes) because it "
                          f"names a folder or file, got {text[:80]!r}")
    return text


def folder(path, root=None, create: bool = False) -> Path:
    """``path``, checked (rule 3): it and every folder between ``root`` and it is a real folder, not a
    link (``root`` itself is the user's: it may be reached through links). ``create``: missing folders
    are made, one by one. ``root`` None: only ``path`` itself is checked."""
    given = Path(path)
    path = Path(os.path.abspath(given))
    root = Path(os.path.abspath(root)) if root is not None else path
    try:
        parts = path.relative_to(root).parts
    except ValueError:
        raise FileRefused(f"{given} is not inside {root}") from None
    if create and not root.exists():
        try:
            missing = root
            while not os.path.lexists(missing.parent) and missing.parent != missing:
                missing = missing.parent
            _ask(missing, replaces=False)
            root.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise _refusal(root, err, "make the folder") from None
    steps = [root] + [root.joinpath(*parts[:i + 1]) for i in range(len(parts))]
    for i, step in enumerate(steps):
        try:
            info = os.lstat(step)
        except FileNotFoundError:
            if not create:
                raise
            try:
                _ask(step, replaces=False)
                os.mkdir(step)
            except FileExistsError:  # made by another process meanwhile, or a dangling link
                pass
            except OSError as err:
                raise _refusal(step, err, "make the folder") from None
            info = os.lstat(step)
        except OSError as err:
            raise _refusal(step, err, "use the folder") from None
        if i == 0 and stat.S_ISLNK(info.st_mode):
            info = os.stat(step)  # the root may be a link the user made (e.g. to a larger disk)
        if not stat.S_ISDIR(info.st_mode):
            what = "a symbolic link" if stat.S_ISLNK(info.st_mode) else kind(info.st_mode)
            raise FileRefused(f"{step} is {what} where a folder of its own is written (a run writes only into real "
                              "folders, never through a link): remove it or choose another folder")
    return given


def private(path) -> Path:
    """The folder ``path`` as this user's alone (for a cache whose files are loaded as code): made if
    missing (its parents too; mode 0700), not a link, owned by this user, and only this user may
    write it. ``FileRefused`` if another user owns it or others may write into it (a shared folder,
    such as ``/tmp``, is never changed: its mode is the system's or its owner's business)."""
    path = Path(path)
    folder(path.parent, path.parent, create=True)
    if not os.path.lexists(path):
        try:
            os.mkdir(path, 0o700)
        except FileExistsError:
            pass
        except OSError as err:
            raise _refusal(path, err, "make the folder") from None
    folder(path, path.parent)
    info = os.lstat(path)
    if hasattr(os, "getuid") and info.st_uid != os.getuid():
        raise FileRefused(f"{path} belongs to another user (uid {info.st_uid}); a folder whose files are loaded as "
                          "code must be this user's own: remove it or choose another")
    if stat.S_IMODE(info.st_mode) & 0o022:  # others may write into it: refused, left as it is
        raise FileRefused(f"{path} may be written by other users (mode {stat.S_IMODE(info.st_mode):04o}); a folder "
                          "whose files are loaded as code must be this user's alone: choose another, or take "
                          "write permission from group and others yourself (chmod go-w)")
    return path


def check_target(path) -> None:
    """``FileRefused`` if a file could not be written at ``path`` later (a tool's output named on its
    command line, checked before its work): something there that is not a regular file or a link,
    or a part of the path that is not a folder."""
    path = Path(path)
    _replaceable(path)
    parent = Path(os.path.abspath(path)).parent
    while not os.path.lexists(parent) and parent.parent != parent:
        parent = parent.parent
    if not os.path.isdir(parent):
        raise FileRefused(f"cannot write {path}: {parent} is not a folder")


def check_chain(path, root) -> None:
    """``folder``'s check of every folder from ``root`` down to ``path`` that exists, making none
    (a check before anything is written: the folders not there yet are made later, checked again)."""
    path, root = Path(os.path.abspath(path)), Path(os.path.abspath(root))
    existing = path
    while not os.path.lexists(existing) and existing != root and existing.parent != existing:
        existing = existing.parent
    if os.path.lexists(existing):
        folder(existing, root)


def check_tree(top) -> None:
    """``FileRefused`` if anything at any depth below the folder ``top`` is a link, a special file,
    or a file with another name (rule 3); nothing there (or no ``top``) is fine."""
    top = Path(top)
    if not os.path.lexists(top):
        return
    folder(top)
    for here, folders, names in walk(top):
        for entry in [*folders, *names]:
            path = Path(here) / entry
            info = os.lstat(path)
            if stat.S_ISDIR(info.st_mode):
                continue
            if not stat.S_ISREG(info.st_mode):
                raise FileRefused(f"{path} is {kind(info.st_mode)} inside {top}, which holds only a run's own files: "
                                  "remove it")
            if info.st_nlink > 1:
                raise FileRefused(f"{path} has {info.st_nlink} names (a hard link) inside {top}, which holds only "
                                  "a run's own files: remove it")


# ---------------------------------------------------------------------------------------------- writing

def write_atomic(path, data, root=None) -> None:
    """Replace ``path`` with ``data`` (bytes, or a list of byte buffers written one after another) by
    rule 5; the folders from ``root`` (default: the file's own folder) down are checked (rule 3).
    A full disk raises ``DiskFull`` and leaves no temporary file."""
    path = Path(path)
    _ask(path)
    folder(path.parent, root if root is not None else path.parent)
    chunks = data if isinstance(data, list) else [data]
    size = sum(len(memoryview(chunk).cast("B")) for chunk in chunks)
    free = free_bytes(path.parent)
    if free is not None and free < size:
        raise DiskFull(path, size)
    _replaceable(path)
    tmp = path.with_name(f"{path.name}.{secrets.token_hex(4)}.tmp")
    if len(tmp.name.encode()) > NAME_BYTES:
        raise FileRefused(f"cannot write {path}: its name is too long for the file system")
    fd, _ = _open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, "write")
    try:
        with os.fdopen(fd, "wb") as f:
            for chunk in chunks:
                f.write(chunk)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)  # a link at ``path`` itself is replaced, not followed
    except OSError as err:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if err.errno in (errno.ENOSPC, errno.EDQUOT):
            raise DiskFull(path, size, quota=err.errno == errno.EDQUOT) from None
        raise _refusal(path, err, "write") from None
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    _sync_folder(path.parent)


def _replaceable(path: Path) -> None:
    """``FileRefused`` unless ``path`` is absent, a regular file or a link (what a write may replace)."""
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        return
    except OSError as err:
        raise _refusal(path, err, "write") from None
    if not (stat.S_ISREG(info.st_mode) or stat.S_ISLNK(info.st_mode)):
        raise FileRefused(f"cannot write {path}: it is {kind(info.st_mode)}, not a regular file; move it away or "
                          "give another name")


def _sync_folder(path) -> None:
    """Flush a folder's entries (a rename) to the disk."""
    try:
        fd = os.open(path, os.O_RDONLY | _DIRECTORY | _CLOEXEC)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def write_text(path, text: str, root=None) -> None:
    """``write_atomic`` of UTF-8 text (a path that is not UTF-8, shown in it, is written escaped)."""
    write_atomic(path, text.encode(errors="backslashreplace"), root)


def open_in_place(path, create: bool = True) -> int:
    """A read-write descriptor of a file written in place (a lock, rows appended), by rules 1 and 2:
    made if missing (``create``), never through a link, never a file with another name."""
    return _open(path, os.O_RDWR | (os.O_CREAT if create else 0), "write", single_link=True)[0]


def open_read(path) -> int:
    """A read-only descriptor of the existing regular file at ``path`` (rule 1), for ``flock``."""
    return _open(path, os.O_RDONLY, "read")[0]


def open_log(path, root):
    """A text file object appending to ``path`` (made if missing, with its folders below ``root``), by
    rules 1 to 3: for a writer that keeps its files open (TorchRL's CSV logger takes it as its own)."""
    path = Path(path)
    folder(path.parent, root, create=True)
    fd = _open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, "append to", single_link=True)[0]
    return os.fdopen(fd, "a")


def open_append(path) -> int:
    """An append-only descriptor of an existing file written in place (rules 1 and 2)."""
    return _open(path, os.O_WRONLY | os.O_APPEND, "append to", single_link=True)[0]


@contextlib.contextmanager
def build(path):
    """A fresh temporary path beside ``path`` for a program to write (a compiler's output); on a clean
    exit of the block it replaces ``path`` (atomically), otherwise it is removed."""
    path = Path(path)
    _ask(path)
    folder(path.parent)
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    os.close(_open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, "write")[0])
    try:
        yield tmp
        info = os.lstat(tmp)
        if not stat.S_ISREG(info.st_mode):
            raise FileRefused(f"{tmp} is {kind(info.st_mode)}, not the file that was to be built")
        os.replace(tmp, path)
    except OSError as err:
        raise _refusal(path, err, "write") from None
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
    _sync_folder(path.parent)


def private_folder(parent, prefix: str) -> Path:
    """A new folder of this process's own inside ``parent`` (made exclusively, mode 0700)."""
    import tempfile

    _ask(Path(parent) / prefix, replaces=False)
    folder(parent)
    try:
        return Path(tempfile.mkdtemp(prefix=prefix, dir=parent))
    except OSError as err:
        raise _refusal(parent, err, "make a folder in") from None


def rename_folder(source, target) -> None:
    """Move the folder ``source`` (one of this process's own, ``private_folder``) to ``target``, which
    must not exist (``FileExistsError`` if another process's landed first)."""
    _ask(target, replaces=False)
    folder(source)
    try:
        os.rename(source, target)
    except OSError as err:
        if err.errno in (errno.EEXIST, errno.ENOTEMPTY):
            raise FileExistsError(errno.EEXIST, "exists already", str(target)) from None
        raise _refusal(target, err, "move a folder to") from None


def extract_tar(data: bytes, into) -> None:
    """Unpack a tar archive (bytes) into the folder ``into`` by tarfile's ``data`` filter: nothing
    outside the folder, no links out of it, no device or FIFO, no setuid bits."""
    import io
    import tarfile

    _ask(into, replaces=False)
    folder(into)
    with tarfile.open(fileobj=io.BytesIO(data)) as archive:
        if not hasattr(tarfile, "data_filter"):  # Python before 3.10.12 / 3.11.4
            raise FileRefused("unpacking an archive safely needs Python 3.11.4 or newer (tarfile's data filter)")
        try:
            archive.extractall(into, filter="data")
        except tarfile.FilterError as err:
            raise FileRefused(f"the archive holds {err}; nothing of it is used") from None


# ---------------------------------------------------------------------------------------------- deleting

def remove(path, missing_ok: bool = True) -> bool:
    """Delete the one file or link named ``path`` (rule 6; a link is removed itself, never what it
    points to); a folder is refused. Returns whether something was removed."""
    _ask(path, replaces=False)
    return _remove(path, missing_ok)


def _remove(path, missing_ok: bool = True) -> bool:
    """``remove`` once the guard (rule 9) has answered for it or for the folder it lies in."""
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        if missing_ok:
            return False
        raise
    if stat.S_ISDIR(info.st_mode):
        raise FileRefused(f"{path} is a folder where a file was expected; it was left as it is")
    try:
        os.unlink(path)
    except FileNotFoundError:
        return False
    except OSError as err:
        raise _refusal(path, err, "remove") from None
    return True


def remove_tree(top) -> None:
    """Delete the folder ``top`` and everything below it, after ``check_tree`` (a link, a special file
    or a hard link inside is refused, and nothing is deleted); a missing folder is fine."""
    top = Path(top)
    if not os.path.lexists(top):
        return
    _ask(top, replaces=False)
    check_tree(top)
    for here, folders, names in walk(top, topdown=False):
        _ask(here, replaces=False)  # once a folder: a deletion's answer is its folder's (rule 9)
        for entry in names:
            _remove(Path(here) / entry)
        for entry in folders:
            try:
                os.rmdir(Path(here) / entry)
            except OSError as err:
                raise _refusal(Path(here) / entry, err, "remove") from None
    try:
        os.rmdir(top)
    except OSError as err:
        raise _refusal(top, err, "remove") from None


# ---------------------------------------------------------------------------------------------- libraries

def load_library(path, sha256: str):
    """``ctypes.CDLL`` of the shared library at ``path`` if its SHA-256 is ``sha256``; ``FileRefused``
    if not. The library loaded is the very file whose bytes were checked (through its descriptor)."""
    import ctypes

    fd, _ = _open(path, os.O_RDONLY, "load")
    try:
        sha = hashlib.sha256()
        while chunk := os.read(fd, 1 << 20):
            sha.update(chunk)
        if sha.hexdigest() != sha256:
            raise FileRefused(f"{path} differs from the library that was built (its SHA-256 does not match the one "
                              "recorded when it was built)")
        proc = f"/proc/self/fd/{fd}"
        try:
            return ctypes.CDLL(proc if os.path.exists(proc) else str(path))
        except OSError as err:
            raise FileRefused(f"cannot load {path}: {str(err)[:200]}") from None
    finally:
        os.close(fd)
