"""Training sessions on demand, each in a forked process, with a fault injected (tests/test_run_folders.py).

Run as ``python -m tests.fault_server``. It imports the project and torch once, then reads one
JSON command per line: ``{"folder": PATH, "overrides": [...], "fault": FAULT or null, "log": PATH}``.
For each it forks a child that trains that run as train.py does (``engine.runner.train_population``
with the settings train.py records) and answers ``{"pid": N}`` at once, then ``{"status": S}``
when the child has ended (its exit status, or minus the signal that killed it). Forking a process
that has already loaded everything starts a session in milliseconds rather than seconds.

A FAULT makes the child signal itself at a chosen moment of its writes:

- ``{"at": "rename", "file": NAME, "nth": K, "signal": SIG, "torn": bool}``: at the K-th
  atomic replacement of NAME (checkpoint.pt, metrics.csv, actor.pt, critic.pt, summary.json) in
  this session; ``torn``: before the rename, with the temporary file cut to half its bytes first
  when SIG is SIGKILL (a write the crash interrupted); otherwise just after the rename;
- ``{"at": "row", "nth": K, "signal": SIG}``: at the K-th row appended to metrics.csv, half of it
  written first when SIG is SIGKILL.

SIGTERM and SIGINT are handled by the run (it stops at the end of the episode, saving a
checkpoint); SIGKILL ends the child where it is.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import traceback
from pathlib import Path

from engine import numerics

numerics.apply(numerics.DEFAULT)  # before torch loads, as train.py does

from engine import outputs, runner  # noqa: E402 (after the numerics)
from engine.config import RunConfig  # noqa: E402
from engine.processes import RunStopped, interrupt  # noqa: E402


def arm(fault: dict) -> None:
    """Patch this (child) process so that it signals itself as ``fault`` says."""
    number = getattr(signal, fault["signal"])
    count = 0

    def now() -> bool:
        nonlocal count
        count += 1
        return count == fault["nth"]

    if fault["at"] == "rename":
        real_replace = os.replace

        def replace(src, dst, *args, **kwargs):
            if Path(dst).name != fault["file"] or not now():
                return real_replace(src, dst, *args, **kwargs)
            if fault["torn"]:
                if number == signal.SIGKILL:
                    size = os.path.getsize(src)
                    os.truncate(src, size // 2)
                os.kill(os.getpid(), number)
                return real_replace(src, dst, *args, **kwargs)
            real_replace(src, dst, *args, **kwargs)
            os.kill(os.getpid(), number)

        os.replace = replace
    elif fault["at"] == "row":
        real_write = outputs.MetricsWriter.write

        def write(self, row):
            if not now():
                return real_write(self, row)
            if number == signal.SIGKILL:
                os.write(self.fd, "".join(f"{row.get(k)}," for k in self.columns)[:25].encode())
            os.kill(os.getpid(), number)
            return real_write(self, row)

        outputs.MetricsWriter.write = write
    else:
        raise ValueError(f"unknown fault {fault}")


def child(command: dict) -> int:
    log = os.open(command["log"], os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(log, 1)
    os.dup2(log, 2)
    for number in (signal.SIGINT, signal.SIGTERM):  # until the run takes them over, as train.py's
        signal.signal(number, interrupt)
    try:
        settings = RunConfig.compose_mapping(*command["overrides"])
        cfg = RunConfig.from_mapping(settings)
        if command.get("fault"):
            arm(command["fault"])
        runner.train_population(cfg, Path(command["folder"]), settings)
    except RunStopped as stopped:
        print(stopped, file=sys.stderr)
        return 130 if "SIGINT" in str(stopped) else 143
    except KeyboardInterrupt as err:  # before the run took the signals over (train.py says so in one line too)
        print(f"Stopped by {err} before training started", file=sys.stderr)
        return 143 if str(err) == "SIGTERM" else 130
    except BaseException:
        traceback.print_exc()
        return 1
    return 0


def main() -> None:
    RunConfig.compose_mapping()  # Hydra loaded and warm before the first fork
    for line in sys.stdin:
        command = json.loads(line)
        pid = os.fork()
        if pid == 0:
            code = 1
            try:
                code = child(command)
            except BaseException:
                traceback.print_exc()
            finally:
                sys.stdout.flush()
                sys.stderr.flush()
                os._exit(code)
        print(json.dumps({"pid": pid}), flush=True)
        _, status = os.waitpid(pid, 0)
        code = -os.WTERMSIG(status) if os.WIFSIGNALED(status) else os.WEXITSTATUS(status)
        print(json.dumps({"status": code}), flush=True)


if __name__ == "__main__":
    main()
