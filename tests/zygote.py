"""Run ``python train.py ARGS`` (or another tool) for the tests without paying torch's imports every time.

Most of a tiny training run's seconds are its process importing torch, TorchRL, TensorDict and
Hydra. A zygote is a process that imports them once (with the default numerics' settings, as
``train.py`` would before torch loads) and then forks a child per command: the child is a new
process (its own pid, signals, exit status, standard streams redirected to files), set up as
``python train.py ARGS`` would be (``sys.argv``, ``sys.path[0]``, the working directory, the
environment), and runs ``train.py`` as ``__main__``. The child's state is the zygote's right
after its imports, which is a fresh process's after the same imports.

``run(script, args, cwd, env, timeout)`` gives a ``subprocess.CompletedProcess``. It falls back to
a real ``python`` process where a forked one could differ or gains nothing: another numerics mode
than the zygote's torch settings (``numerics=native``), a sweep through a launcher with worker
processes (``-m`` without ``hydra/launcher=basic``: its workers import for themselves, and a forked
parent's exit waited on joblib's workers for minutes; the basic launcher runs the jobs in the
process itself, so such a sweep is forked), a platform without ``fork``, or ``RACING_TEST_ZYGOTE=0``.
One zygote per test process and environment (``VOLATILE`` variables aside: each child gets the
environment it was asked for), started on first use and stopped at exit.
"""

from __future__ import annotations

import atexit
import json
import os
import socket
import struct
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PRELOAD = ["torch", "tensordict", "torchrl.envs", "torchrl.objectives", "torchrl.collectors", "torchrl.data",
           "hydra", "omegaconf", "engine.runner", "engine.setup", "learners.td.learner",
           "learners.monte_carlo.learner", "racing.torchrl_env"]
# Variables that change from test to test and that nothing reads while importing: they do not start a zygote
# of their own (pytest sets PYTEST_CURRENT_TEST to the running test's name, so a test passing
# dict(os.environ) would otherwise start one zygote per test, about 3 s and 350 MB each).
VOLATILE = ("PYTEST_CURRENT_TEST",)


def _send(conn: socket.socket, message: dict) -> None:
    data = json.dumps(message).encode()
    conn.sendall(struct.pack("!I", len(data)) + data)


def _receive(conn: socket.socket) -> dict | None:
    header = _exactly(conn, 4)
    if header is None:
        return None
    data = _exactly(conn, struct.unpack("!I", header)[0])
    return None if data is None else json.loads(data)


def _exactly(conn: socket.socket, size: int) -> bytes | None:
    chunks, got = [], 0
    while got < size:
        chunk = conn.recv(size - got)
        if not chunk:
            return None
        chunks.append(chunk)
        got += len(chunk)
    return b"".join(chunks)


def _child(request: dict) -> None:
    """In the forked child: become ``python SCRIPT ARGS`` and run it; never returns."""
    code = 1
    try:
        os.chdir(request["cwd"])
        os.environ.clear()
        os.environ.update(request["env"])
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        for fd, path in ((1, request["stdout"]), (2, request["stderr"])):
            target = os.open(path, os.O_WRONLY | os.O_TRUNC)
            os.dup2(target, fd)
            os.close(target)
        command = request["command"]
        import runpy

        try:
            if command[0] == "-m":  # python -m MODULE ARGS: the working directory first on the path
                sys.argv = [command[1], *command[2:]]
                sys.path[0] = os.getcwd()
                runpy.run_module(command[1], run_name="__main__", alter_sys=True)
            else:
                sys.argv = list(command)
                sys.path[0] = os.path.dirname(os.path.abspath(command[0]))
                runpy.run_path(command[0], run_name="__main__")
            code = 0
        except SystemExit as exit:  # as the interpreter ends: None is 0, a message goes to stderr with 1
            code = exit.code if isinstance(exit.code, int) else 0 if exit.code is None else 1
            if code == 1 and not isinstance(exit.code, int):
                print(exit.code, file=sys.stderr)
        except BaseException:
            import traceback

            traceback.print_exc()
            code = 1
        atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:
                pass
        os._exit(code)


def serve(path: str) -> None:
    """The zygote: import, then fork a child per request on the Unix socket at ``path``."""
    from engine import numerics

    numerics.apply(numerics.DEFAULT)
    import importlib

    for name in PRELOAD:
        importlib.import_module(name)
    from engine.processes import exit_with_parent

    exit_with_parent()  # a test process killed outright (no atexit) leaves no zygote behind
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(path)
    server.listen(8)
    print("ready", flush=True)
    while True:
        conn, _ = server.accept()
        with conn:
            request = _receive(conn)
            if request is None:
                continue
            if request.get("stop"):
                return
            pid = os.fork()
            if pid == 0:
                server.close()
                conn.close()
                _child(request)
            _send(conn, {"pid": pid})
            _, status = os.waitpid(pid, 0)
            _send(conn, {"status": os.waitstatus_to_exitcode(status)})


class Zygote:
    def __init__(self, env: dict):
        self.env = dict(env)
        self.folder = tempfile.mkdtemp(prefix="racing-zygote-")
        self.path = os.path.join(self.folder, "socket")
        self.process = subprocess.Popen([sys.executable, "-m", "tests.zygote", self.path], cwd=ROOT, env=self.env,
                                        stdout=subprocess.PIPE, stdin=subprocess.DEVNULL)
        line = self.process.stdout.readline()
        if line.strip() != b"ready":
            self.process.kill()
            raise RuntimeError("the test zygote did not start")
        atexit.register(self.stop)

    def run(self, command: list[str], cwd: Path, timeout: float,
            env: dict | None = None) -> subprocess.CompletedProcess:
        """``command`` forked, in ``cwd`` with ``env`` (default: the zygote's own environment)."""
        with tempfile.TemporaryDirectory(dir=self.folder) as folder:
            out, err = os.path.join(folder, "out"), os.path.join(folder, "err")
            for path in (out, err):
                open(path, "w").close()
            conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            conn.connect(self.path)
            with conn:
                _send(conn, {"command": command, "cwd": str(cwd), "env": dict(self.env if env is None else env),
                             "stdout": out, "stderr": err})
                pid = _receive(conn)["pid"]
                conn.settimeout(timeout)
                try:
                    reply = _receive(conn)
                except socket.timeout:
                    os.kill(pid, 9)
                    raise subprocess.TimeoutExpired([sys.executable, *command], timeout) from None
            return subprocess.CompletedProcess([sys.executable, *command], reply["status"], Path(out).read_text(),
                                               Path(err).read_text())

    def stop(self) -> None:
        self.process.stdout.close()
        if self.process.poll() is None:
            try:
                conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                conn.connect(self.path)
                with conn:
                    _send(conn, {"stop": True})
                self.process.wait(timeout=10)
            except (OSError, subprocess.TimeoutExpired):
                self.process.kill()
        import shutil

        shutil.rmtree(self.folder, ignore_errors=True)


_zygotes: dict[str, Zygote] = {}


def forkable(command: list) -> bool:
    """Whether ``run`` forks ``command`` from a zygote (see the module's docstring)."""
    command = [str(part) for part in command]
    args = command[2:] if command[0] == "-m" else command[1:]
    return (hasattr(os, "fork") and os.environ.get("RACING_TEST_ZYGOTE", "1") != "0"
            and not any(a.startswith("numerics=") and a not in ("numerics=fma", "numerics=portable") for a in args)
            and (not {"-m", "--multirun"} & set(args) or "hydra/launcher=basic" in args))


def run(command: list, cwd: Path, env: dict, timeout: float = 600) -> subprocess.CompletedProcess:
    """``subprocess.run([python, *command], cwd=cwd, env=env, capture_output=True, text=True)``
    (``command``: a script and its arguments, or ``-m``, a module and its arguments), forked from a
    zygote where that gives the same process (see the module's docstring)."""
    command = [str(part) for part in command]
    if forkable(command):
        key = json.dumps({k: v for k, v in env.items() if k not in VOLATILE}, sort_keys=True)
        zygote = _zygotes.get(key)
        if zygote is None:
            zygote = _zygotes[key] = Zygote(env)
        return zygote.run(command, cwd, timeout, env)
    return subprocess.run([sys.executable, *command], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=timeout)


if __name__ == "__main__":
    serve(sys.argv[1])
