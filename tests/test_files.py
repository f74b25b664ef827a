"""The one door's rules (door/files.py), each tested once here for every caller: what reaches a
file goes through these functions (tests/test_one_door.py checks that), so a rule held here holds
for every tool. Special files are made in tmp_path; an alarm ends any test that would block."""

from __future__ import annotations

import errno
import hashlib
import os
import signal
import stat
from contextlib import contextmanager
from pathlib import Path

import pytest

from door import files
from door.files import FileRefused


class Hung(AssertionError):
    """A block that did not end in time."""


@contextmanager
def no_hang(seconds: int = 10):
    """``Hung`` instead of blocking (a FIFO opened without O_NONBLOCK would wait for a writer forever)."""
    def hung(number, frame):
        raise Hung(f"blocked for {seconds} s")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.fixture
def specials(tmp_path) -> dict[str, Path]:
    """One of each thing that is not a regular file of its own, and a regular file outside."""
    outside = tmp_path / "outside.txt"
    outside.write_text("the user's own file\n")
    made = {"fifo": tmp_path / "fifo", "folder": tmp_path / "folder", "link": tmp_path / "link",
            "dangling": tmp_path / "dangling", "hardlink": tmp_path / "hardlink", "socket": tmp_path / "socket"}
    os.mkfifo(made["fifo"])
    made["folder"].mkdir()
    made["link"].symlink_to(outside)
    made["dangling"].symlink_to(tmp_path / "nowhere")
    os.link(outside, made["hardlink"])
    import socket

    server = socket.socket(socket.AF_UNIX)
    server.bind(str(made["socket"]))
    server.close()
    made["device"] = Path("/dev/null")
    made["outside"] = outside
    return made


def test_rule_1_only_regular_files_are_read_checked_on_the_descriptor(specials):
    with no_hang():
        for kind in ("fifo", "folder", "link", "socket", "device"):
            with pytest.raises(FileRefused) as refused:
                files.read(specials[kind], 1000, "summary")
            assert str(specials[kind]) in str(refused.value)
            with pytest.raises(FileRefused):
                files.digest(specials[kind])
        with pytest.raises(FileRefused, match="symbolic link"):
            files.read(specials["link"], 1000)
        assert files.read(specials["link"], 1000, follow=True) == b"the user's own file\n"  # a user's input
        with pytest.raises(FileRefused, match="FIFO"):
            files.read(specials["fifo"], 1000, follow=True)  # followed or not, never a FIFO
        with pytest.raises(FileRefused, match="character device"):
            files.read(specials["device"], 1000, follow=True)
        with pytest.raises(FileNotFoundError):
            files.read(specials["fifo"].parent / "missing", 1000)  # a missing file stays one


def test_rule_2_a_file_written_in_place_has_one_link(specials, tmp_path):
    with no_hang():
        for opener in (files.open_in_place, files.open_append):
            with pytest.raises(FileRefused, match="2 names"):
                opener(specials["hardlink"])
            for kind in ("fifo", "link", "dangling", "folder", "socket"):
                with pytest.raises(FileRefused):
                    opener(specials[kind])
        assert specials["outside"].read_text() == "the user's own file\n"
        fd = files.open_in_place(tmp_path / "lock")  # made when missing
        os.close(fd)
        # a replacing write to a hard link makes a new file: the other name keeps its content
        files.write_atomic(specials["hardlink"], b"new")
        assert specials["hardlink"].read_bytes() == b"new" and specials["outside"].read_text() == "the user's own file\n"


def test_rule_3_folders_on_the_way_are_real_folders(tmp_path, specials):
    root = tmp_path / "sweep"
    files.folder(root / "a" / "b", root, create=True)
    assert (root / "a" / "b").is_dir()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (root / "a" / "member").symlink_to(elsewhere)
    with pytest.raises(FileRefused, match="symbolic link where a folder of its own is written"):
        files.folder(root / "a" / "member" / "logs", root, create=True)
    assert list(elsewhere.iterdir()) == []  # nothing made through the link
    (root / "a" / "file").write_text("")
    with pytest.raises(FileRefused):
        files.folder(root / "a" / "file" / "x", root, create=True)
    with pytest.raises(FileRefused, match="not inside"):
        files.folder(tmp_path / "other", root)
    linked_root = tmp_path / "linked_root"  # the root itself is the user's: it may be a link
    linked_root.symlink_to(root)
    assert files.folder(linked_root / "a" / "b", linked_root) == linked_root / "a" / "b"
    # check_tree: nothing below a folder a logger writes into is a link, special file or hard link
    logs = tmp_path / "logs" / "scalars" / "train"
    logs.mkdir(parents=True)
    (logs / "x.csv").write_text("1\n")
    files.check_tree(tmp_path / "logs")
    for make in (lambda p: p.symlink_to(specials["outside"]), lambda p: os.link(specials["outside"], p), os.mkfifo):
        make(logs / "total_reward.csv")
        with pytest.raises(FileRefused, match="total_reward.csv"):
            files.check_tree(tmp_path / "logs")
        (logs / "total_reward.csv").unlink()
    assert specials["outside"].read_text() == "the user's own file\n"


def test_rule_4_reads_are_bounded_and_a_huge_file_is_refused_unread(tmp_path):
    huge = tmp_path / "metrics.csv"
    with open(huge, "wb") as f:
        f.truncate(3 * 2**30)  # sparse: 3 GB that take no disk
    with pytest.raises(FileRefused, match=r"3,221,225,472 bytes, more than a metrics.csv holds"):
        files.read(huge, 2**20, "metrics.csv")
    with pytest.raises(FileRefused, match="more than 10 bytes"):
        files.read(Path("/proc/self/status"), 10, follow=True)  # a size the system does not report
    small = huge.with_name("small")
    small.write_bytes(b"0123456789")
    assert files.read(small, 10) == b"0123456789"  # exactly the limit is fine


def test_rule_5_writes_are_atomic_and_never_replace_a_folder_or_special_file(tmp_path, specials):
    target = tmp_path / "summary.json"
    files.write_atomic(target, [b"a", b"b"])
    assert target.read_bytes() == b"ab" and [p.name for p in tmp_path.glob("*.tmp")] == []
    with no_hang():
        for kind in ("fifo", "folder", "socket"):
            with pytest.raises(FileRefused, match="not a regular file|a folder"):
                files.write_atomic(specials[kind], b"x")
    assert stat.S_ISFIFO(os.lstat(specials["fifo"]).st_mode)  # left as it was
    files.write_atomic(specials["link"], b"x")  # a link at the name itself is replaced, not followed
    assert not specials["link"].is_symlink() and specials["outside"].read_text() == "the user's own file\n"
    os.mkfifo(tmp_path / "summary.json.tmp")  # an older writer's temporary name, now a FIFO: never opened
    with no_hang():
        files.write_atomic(target, b"c")
    assert target.read_bytes() == b"c"
    with pytest.raises(FileRefused, match="too long"):
        files.write_atomic(tmp_path / ("x" * 250), b"x")
    with pytest.raises(FileRefused, match="a part of the path is not a folder|is a file"):
        files.write_atomic(target / "inside", b"x")


def test_rule_6_deletions_remove_what_is_named_and_never_follow(tmp_path, specials):
    assert files.remove(specials["link"]) and specials["outside"].exists()
    assert files.remove(specials["fifo"]) and not os.path.lexists(specials["fifo"])
    assert not files.remove(tmp_path / "missing")
    with pytest.raises(FileRefused, match="is a folder"):
        files.remove(specials["folder"])
    tree = tmp_path / "logs"
    (tree / "a").mkdir(parents=True)
    (tree / "a" / "x.csv").write_text("1")
    (tree / "a" / "draft.tex").symlink_to(specials["outside"])
    with pytest.raises(FileRefused, match="draft.tex"):
        files.remove_tree(tree)
    assert (tree / "a" / "x.csv").exists() and specials["outside"].exists()  # nothing deleted
    (tree / "a" / "draft.tex").unlink()
    files.remove_tree(tree)
    assert not tree.exists()


def test_rule_7_names_are_names():
    for good in ("spg_p", "memory", "seed3", "a.b"):
        assert files.name(good, "algo.name") == good
    for bad in ("", ".", "..", "../x", "a/b", "/abs", "a\0b", "x" * 256):
        with pytest.raises(FileRefused, match="algo.name must be a name"):
            files.name(bad, "algo.name")


def test_a_library_is_loaded_only_as_the_bytes_recorded(tmp_path):
    from learners import kernels

    if kernels.unavailable_reason() is not None:
        pytest.skip(f"the kernels cannot be built here: {kernels.unavailable_reason()}")
    path, digest = kernels._build()
    assert files.load_library(path, digest) is not None
    with pytest.raises(FileRefused, match="differs from the library that was built"):
        files.load_library(path, hashlib.sha256(b"other").hexdigest())


def test_the_door_turns_system_errors_into_one_sentence(tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root reads and writes through permissions")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        with pytest.raises(FileRefused, match="permission denied"):
            files.write_atomic(locked / "x", b"x")
    finally:
        locked.chmod(0o700)


def test_a_disk_out_of_file_entries_says_so(tmp_path, monkeypatch):
    """On 258b7c4 a disk with bytes to spare but no inodes left was reported as "no space left ... 52,342,784
    (bytes) are free": it says what ran out, as it does for a quota."""
    real = os.statvfs(tmp_path)

    class NoEntries:  # the device's own numbers, but no entry left
        f_bavail, f_frsize, f_blocks, f_bfree = real.f_bavail, real.f_frsize, real.f_blocks, real.f_bfree
        f_files, f_favail = real.f_files or 1000, 0

    monkeypatch.setattr(files.os, "statvfs", lambda folder: NoEntries())
    message = str(files._refusal(tmp_path / "x", OSError(errno.ENOSPC, "full"), "write"))
    assert "has no file entries (inodes) left (though " in message and "delete some files" in message, message
    quota = str(files._refusal(tmp_path / "x", OSError(errno.EDQUOT, "quota"), "write"))
    assert quota.startswith("this user's disk quota is used up"), quota
    monkeypatch.undo()
    full = str(files._refusal(tmp_path / "x", OSError(errno.ENOSPC, "full"), "write"))
    assert full.startswith(f"no space left on the device of {tmp_path / 'x'}"), full


def test_errno_names_cover_what_the_door_reports():
    for code in (errno.ELOOP, errno.ENXIO, errno.EISDIR, errno.ENAMETOOLONG, errno.EROFS, errno.EACCES):
        err = files._refusal(Path("/x"), OSError(code, os.strerror(code)), "write")
        assert isinstance(err, FileRefused) and str(err).startswith("cannot write /x: ")
    assert isinstance(files._refusal(Path("/x"), OSError(errno.ENOSPC, "full"), "write"), files.DiskFull)
