"""The worker pool every tool runs its jobs in (torch-free until a job imports it).

``run_jobs(function, jobs, processes, numerics=mode)`` returns ``[function(job) for job in jobs]``, in order,
computed in up to ``processes`` spawned worker processes (in this process when one would do). What it
promises, whatever the jobs do:

- a stop reaches every worker: SIGINT or SIGTERM to the tool (``engine.processes.run_tool``'s handlers
  raise ``KeyboardInterrupt`` in it) terminates every worker at once and waits for them, so no child is
  left running and the tool ends in its one line ("stopped by SIGTERM before it finished"), never a
  table of the jobs that happened to finish (nothing is returned);
- a worker whose parent is gone (``kill -9`` of the tool) ends within a second
  (``engine.processes.exit_with_parent``);
- a worker ignores a terminal's Ctrl-C (sent to the whole process group): its parent decides, and
  stops it;
- each worker writes only where the tool may (``engine.tool_output``'s guard, if the tool's process has it);
- each worker applies the tool's numerics (``engine.numerics.apply``) before any job, so that a job
  computes the same bits in a worker as in the tool's own process;
- a job's exception ends the pool the same way and is raised in the tool (its first, in job order).

Training populations split over processes (``processes=N``) use ``engine.runner``'s own pool, which
passes a stop on to each part so that each saves its checkpoint first.
"""

from __future__ import annotations

import signal


_STOPS = {signal.SIGINT, signal.SIGTERM}


def _start_worker() -> None:
    """Cannot fail (a pool whose initializer raises starts workers for ever): signals only."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides (a terminal's Ctrl-C reaches the group)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOPS)  # held while the parent started it (run_jobs)


_applied: list[str] = []  # the numerics this worker applied


def _call(task: tuple):
    function, mode, guarded, job = task
    from door import files
    from engine.processes import exit_with_parent

    exit_with_parent()  # once per process
    if guarded and not files.guarded():  # a tool's worker writes where the tool may (engine.tool_output)
        from engine import tool_output

        tool_output.guard()
    if mode is not None and not _applied:
        from engine import numerics

        numerics.apply(mode)
        _applied.append(mode)
    return function(job)


def run_jobs(function, jobs, processes: int, numerics: str | None = None) -> list:
    """``[function(job) for job in jobs]``, in up to ``processes`` worker processes (see the module's
    docstring); ``function`` and the jobs must pickle (a module-level function). ``numerics``: the mode each
    worker applies first (this process's is applied by the tool itself)."""
    jobs = list(jobs)
    if processes <= 1 or len(jobs) <= 1:
        return [function(job) for job in jobs]
    from engine.processes import spawn_context

    # a stop while the workers are being started would cut the data each reads at its start (a worker's EOFError
    # traceback after the tool's one line): held until they all are, then delivered here
    held = signal.pthread_sigmask(signal.SIG_BLOCK, _STOPS)
    try:
        pool = spawn_context().Pool(min(processes, len(jobs)), initializer=_start_worker)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)
    try:
        from door import files

        results = pool.map(_call, [(function, numerics, files.guarded(), job) for job in jobs], chunksize=1)
        pool.close()
        return results
    except BaseException:
        pool.terminate()  # SIGTERM to every worker, then joined: none is left running
        raise
    finally:
        pool.join()
