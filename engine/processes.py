"""Worker processes that end with the process that started them, and the allocator setting a
training process runs with (torch-free).

``processes=N`` (``engine.runner``) and ``baseline.py --jobs`` train in spawned worker processes.
Killed with SIGINT from a terminal, the whole process group stops; but a parent killed alone
(``kill PID``, a launcher's timeout) would leave its workers training on, and a rerun of the same
command would then write the same run folders twice at once. A worker calls
``exit_with_parent()`` first: a daemon thread that ends the worker at once when its parent is
gone, as if it had been killed, so its last checkpoint is where a rerun resumes.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from pathlib import Path


_watching: set[int] = set()  # the parents this process already watches
_deferred_since: dict[int, float] = {}  # signal -> when a library's code first made it wait


def run_tool(name: str, main) -> int:
    """A command-line tool's ``main()`` (score.py, evaluate.py, tracks.py, drive.py, report.py,
    imitate.py, baseline.py): SIGINT or SIGTERM ends it with one line and status 130 or 143 instead
    of a traceback. The readers write their files whole at their end, so nothing is left half
    written; baseline.py's interrupted run folder stays unfinished (no summary), as train.py's.
    A file the tool may not read or write (``door.files.FileRefused``: a FIFO, a link, a folder
    where a file goes, a read-only disk, a name too long) ends it with that one line and status 2
    (1 for a full disk). Every write it makes asks the output writer first (``engine.tool_output.guard``: never
    inside a run folder it does not write as that run's writer, never over a file it reads)."""
    from door.files import DiskFull, FileRefused
    from engine import tool_output

    readable_output()
    tool_output.guard()

    signal.signal(signal.SIGTERM, interrupt)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # an ignored SIGINT stays ignored
        signal.signal(signal.SIGINT, interrupt)
    try:
        return main()
    except FileRefused as err:
        print(f"{name}: {err}", file=sys.stderr)
        return 1 if isinstance(err, DiskFull) else 2
    except KeyboardInterrupt as err:
        received = str(err) or "SIGINT"
        print(f"{name}: stopped by {received} before it finished", file=sys.stderr)
        return 143 if received == "SIGTERM" else 130


# The project's own packages (pyproject.toml's list; tests/test_signals.py keeps the two equal):
# code of theirs is where a stop may raise, wherever the project is installed.
PROJECT_PACKAGES = ("door", "racing", "losses", "collectors", "learners", "engine", "analysis", "benchmark",
                    "external", "pupil", "hydra_plugins")


def _library(frame) -> bool | None:
    """Whose code ``frame`` runs: True for an installed library's, False for the project's or a
    script's, None for the standard library's (which decides nothing: contextlib's ``__exit__`` runs
    for whoever called it)."""
    module = (frame.f_globals.get("__name__") or "").split(".")[0]
    filename = frame.f_code.co_filename
    if module in sys.stdlib_module_names or filename.startswith("<frozen"):
        return None
    installed = any(f"{os.sep}{place}{os.sep}" in filename for place in ("site-packages", "dist-packages"))
    return installed and module not in PROJECT_PACKAGES


# Parts of torch that are plain Python called from Python: a signal interrupting them is a library's (it
# waits at most a second), not a callback's from torch's C++.
TORCH_PLAIN = ("nn" + os.sep, "utils" + os.sep + "_contextlib.py", "autograd" + os.sep + "grad_mode.py",
               "optim" + os.sep, "_tensor.py", "functional.py")


def deferred(number: int, frame) -> bool:
    """Whether a signal handler's exception must wait, the signal being sent again 50 ms later
    until it lands where raising is safe:

    - while torch's C++ may be running torch's Python code as a callback, where an exception aborts
      the whole process (``terminate called after throwing pybind11::error_already_set``): while
      torch imports (a module body of torch's on the stack), or when the code interrupted is torch's
      own outside its plain-Python parts (``TORCH_PLAIN``: modules, grad-mode wrappers, optimisers).
      A torch frame further out (``@torch.no_grad()`` around a planner's step, a Module's call around
      the project's forward) does not make the signal wait: it once kept SIGINT waiting for as long
      as a planner evaluated;
    - for at most a second, when the code the signal interrupted is an installed library's (the
      innermost frame outside the standard library): an exception raised while omegaconf sets a
      value leaves its objects half changed, and its clean-up then raises an unrelated error, a
      traceback instead of one line. A library that waits (joblib for its workers) is interrupted
      after that second."""
    torch_dir = os.sep + "torch" + os.sep
    decided, inner, innermost = False, frame, True
    while inner is not None:
        filename = inner.f_code.co_filename
        if torch_dir in filename and (inner.f_code.co_name == "<module>" or innermost and not any(
                f"{torch_dir}{part}" in filename for part in TORCH_PLAIN)):
            decided = True
            break
        if innermost and _library(inner) is not None:  # the innermost frame outside the standard library
            innermost = False
        inner = inner.f_back
    while not decided and frame is not None:
        library = _library(frame)
        if library is not None:
            now = time.monotonic()
            decided = library and now - _deferred_since.setdefault(number, now) < 1.0
            break
        frame = frame.f_back
    if not decided:
        _deferred_since.pop(number, None)
    else:
        timer = threading.Timer(0.05, os.kill, (os.getpid(), number))
        timer.daemon = True
        timer.start()
    return decided


def interrupt(number: int, frame) -> None:
    """A SIGINT or SIGTERM handler for a tool's work: ``KeyboardInterrupt`` named after the signal,
    raised where raising is safe (``deferred``)."""
    if not deferred(number, frame):
        raise KeyboardInterrupt(signal.Signals(number).name)


def check_start_seeds(parser, seed: int, episodes: int) -> None:
    """``parser.error`` in one line unless every episode's start seed, ``seed + k`` for k < ``episodes``, is a seed
    (in [0, 2**32)); ``episodes`` at least 1, checked before."""
    if not 0 <= seed <= 2**32 - episodes:
        parser.error(f"--seed must be in [0, 2**32 - --episodes] (episode k starts from seed + k), got {seed}")


def readable_output() -> None:
    """Standard output and error print what cannot be encoded (a folder name that is not UTF-8)
    escaped, instead of ending the tool in a ``UnicodeEncodeError``; the project's own warnings (a
    fallback to other numerics, say) print as one plain line, without the source line Python adds."""
    import warnings

    for stream in (sys.stdout, sys.stderr):
        reconfigure = getattr(stream, "reconfigure", None)
        if reconfigure is not None:
            try:
                reconfigure(errors="backslashreplace")
            except (ValueError, OSError):
                pass
    if getattr(warnings.formatwarning, "racing_plain", False):
        return
    default = warnings.formatwarning

    def formatwarning(message, category, filename, lineno, line=None):
        if _in_project(filename):
            return f"Warning: {message}\n"
        return default(message, category, filename, lineno, line)

    formatwarning.racing_plain = True
    warnings.formatwarning = formatwarning


def _in_project(filename: str) -> bool:
    """Whether ``filename`` is one of the project's own modules (a package of ``PROJECT_PACKAGES``)."""
    return any(part in PROJECT_PACKAGES for part in Path(filename).parts[-3:-1])  # a package, or one's subpackage


def exit_with_parent(poll_seconds: float = 1.0) -> None:
    """End this process (``os._exit(1)``) within ``poll_seconds`` of its parent's death (once per
    process: a pool worker calls it for every task)."""
    parent = os.getppid()
    if parent in _watching:
        return
    _watching.add(parent)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_seconds)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def spawn_context():
    """multiprocessing's ``spawn`` context, usable inside a joblib (loky) worker too: there the
    global start method reads ``loky``, which a spawned child would try to set and cannot, so it
    is set back to ``spawn`` first."""
    import multiprocessing

    if multiprocessing.get_start_method(allow_none=True) not in (None, "fork", "spawn", "forkserver"):
        multiprocessing.set_start_method("spawn", force=True)
    return multiprocessing.get_context("spawn")


_KEEP = 1 << 30  # bytes: glibc's thresholds (M_TRIM_THRESHOLD, M_MMAP_THRESHOLD) set by keep_freed_memory
_kept = False


def keep_freed_memory() -> bool:
    """Let glibc's allocator keep freed memory for reuse instead of handing it back to the OS.

    By default glibc serves large blocks (torch's tensors of a population's minibatch) with fresh
    ``mmap`` pages and trims the heap's top when it is freed, so every step of a large population
    page-faults its activations in again (5-7% of a profile of SPG-p at 25 members). With both
    thresholds at 1 GiB, freed blocks stay in the heap and the next step reuses them: SPG-p's
    population of 25 trains about 13% faster, PPO's 5% (``NOTES.md``); the process holds its
    peak working set. Only where memory comes from: no number a run computes changes (the golden
    runs check it). Once per process; a no-op (False) where the C library is not glibc.
    """
    global _kept
    if _kept:
        return True
    import ctypes
    import ctypes.util
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.restype, mallopt.argtypes = ctypes.c_int, [ctypes.c_int, ctypes.c_int]
    m_trim_threshold, m_mmap_threshold = -1, -3  # malloc.h
    _kept = bool(mallopt(m_trim_threshold, _KEEP)) and bool(mallopt(m_mmap_threshold, _KEEP))
    return _kept


class RunStopped(KeyboardInterrupt):
    """A run stopped by SIGINT or SIGTERM; the message is the one line to show (where it was saved)."""


STOP_FILE = ".stop"  # in a sweep's folder: the sweep was asked to stop (its content: the signal's name)


def replaceable(handler):
    """``handler`` as a signal handler that ``StopSignals`` may stand in for while a run trains (the
    early handler of train.py, a sweep's)."""
    def handle(number, frame):
        return handler(number, frame)

    handle.racing_replaceable = True
    return handle


def _is_ours_to_replace(handler) -> bool:
    return handler in (signal.default_int_handler, signal.SIG_DFL) or getattr(handler, "racing_replaceable", False)


class StopSignals:
    """For the block: the first SIGINT or SIGTERM asks the run to stop at the end of its episode
    (``requested`` names the signal); a second one stops it at once (``KeyboardInterrupt``).

    A stop asked for elsewhere counts as the first signal: ``shared`` (a ``multiprocessing`` value
    holding a signal's number, set by the process that started this one: a split population's
    parent) and ``stop_file`` (a sweep's ``.stop``, written when the sweep was asked to stop).

    Installed only in the main thread and only over Python's default handlers (or those marked
    ``replaceable``): a launcher that handles the signals itself (submitit's requeue on SLURM)
    keeps its own."""

    def __init__(self, shared=None, stop_file: Path | None = None):
        self.received: str | None = None  # the first signal this process received
        self.passed_on: str | None = None  # a stop asked for elsewhere
        self.shared, self.stop_file = shared, stop_file
        self._previous: dict = {}

    @property
    def requested(self) -> str | None:
        """The name of the signal that asked the run to stop (None: none did)."""
        if self.received is None and self.passed_on is None:
            if self.shared is not None and self.shared.value:
                self.passed_on = signal.Signals(self.shared.value).name
            elif self.stop_file is not None:
                self.passed_on = read_stop_file(self.stop_file)
        return self.received or self.passed_on

    def _handle(self, number, frame) -> None:
        if self.received is not None:  # the second signal this process received (a stop passed on counts not)
            raise KeyboardInterrupt
        self.received = signal.Signals(number).name

    def __enter__(self) -> "StopSignals":
        if threading.current_thread() is threading.main_thread():
            for number in (signal.SIGINT, signal.SIGTERM):
                if _is_ours_to_replace(signal.getsignal(number)):
                    self._previous[number] = signal.signal(number, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)


def _between_jobs(number, frame) -> None:
    """A signal to a sweep's worker between its jobs: the sweep's process has it too and stops the sweep."""


_between_jobs.racing_replaceable = True


def idle_between_jobs() -> None:
    """In a sweep's worker process (joblib's), SIGINT and SIGTERM outside a run's training do nothing
    (each run's ``StopSignals`` stands in for this while it trains): a second Ctrl-C that reaches a
    worker between two jobs must not end it with a traceback. Only over the default handlers."""
    if threading.current_thread() is threading.main_thread():
        for number, default in ((signal.SIGINT, signal.default_int_handler), (signal.SIGTERM, signal.SIG_DFL)):
            if signal.getsignal(number) is default:
                signal.signal(number, _between_jobs)


def read_stop_file(path: Path) -> str | None:
    """The signal named by a sweep's stop file (None: there is none)."""
    from door import files

    try:
        text = files.read_text(path, 64, "stop file").strip()
    except FileNotFoundError:
        return None
    except (OSError, files.FileRefused):  # something is there that is not the stop file: stop all the same
        return "SIGTERM"
    return text if text in ("SIGINT", "SIGTERM") else "SIGTERM"


def write_stop_file(path: Path, name: str) -> None:
    """Ask every job of a sweep to stop (``StopSignals``'s ``stop_file``), never through a link."""
    from door import files

    try:
        files.write_atomic(path, (name + "\n").encode())  # replaces a link there, never writes through it
    except (OSError, files.FileRefused):
        pass


def stop_at_once(pids: list[int]) -> None:
    """Stop these runs at once: two SIGINTs each (a run's second signal; apart, so neither is lost
    in the other), whatever they received before."""
    for _ in range(2):
        for pid in pids:
            try:
                os.kill(pid, signal.SIGINT)
            except ProcessLookupError:
                pass
        time.sleep(0.2)


def descendants(pid: int | None = None) -> list[int]:
    """The processes started by ``pid`` (default: this one) and theirs, from /proc (Linux; [] elsewhere)."""
    from door import files

    pid = os.getpid() if pid is None else pid
    children: dict[int, list[int]] = {}
    try:
        entries = os.listdir("/proc")
    except OSError:
        return []
    for entry in entries:
        if entry.isdigit():
            try:
                fields = files.read_text(f"/proc/{entry}/stat", 1 << 16, "process status",
                                         follow=True).rsplit(")", 1)[1].split()
                children.setdefault(int(fields[1]), []).append(int(entry))
            except (OSError, IndexError, ValueError):  # FileRefused is a ValueError
                continue
    found, queue = [], [pid]
    while queue:
        for child in children.get(queue.pop(), []):
            found.append(child)
            queue.append(child)
    return found
