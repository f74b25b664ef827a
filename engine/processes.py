"""Worker processes that end with the process that started them (torch-free).

``processes=N`` (``engine.runner``) and ``baseline.py --jobs`` train in spawned worker processes.
Killed with SIGINT from a terminal, the whole process group stops; but a parent killed alone
(``kill PID``, a launcher's timeout) would leave its workers training on, and a rerun of the same
command would then write the same run folders twice at once. A worker calls
``exit_with_parent()`` first: a daemon thread that ends the worker at once when its parent is
gone, as if it had been killed, so its last checkpoint is where a rerun resumes.
"""

from __future__ import annotations

import os
import threading
import time


_watching: set[int] = set()  # the parents this process already watches


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
