"""Progress of a training run: a live bar on a terminal, plain lines in a file.

On a terminal (``stream.isatty()``) the bar redraws in place. Anywhere else (a SLURM job's
log, CI, ``nohup``, a pipe) carriage-return frames would pile up into one enormous line, so
the run prints one plain line every ``every`` episodes (about 20 lines a run) and whenever
``interval`` seconds have passed since the last one, each well under 200 characters:

    spg_p/hybrid/5 seeds: episode 40/201 (20%), reward 85.3, last20 71.2, 1:02 elapsed, ~4:10 left
"""

from __future__ import annotations

import sys
import threading
import time


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    hours, rest = divmod(seconds, 3600)
    return f"{hours}:{rest // 60:02d}:{rest % 60:02d}" if hours else f"{rest // 60}:{rest % 60:02d}"


class Progress:
    """``update(reward=..., last20=..., diverged=...)`` once per episode; ``close()`` at the end."""

    def __init__(self, description: str, total: int, initial: int = 0, enabled: bool = True, stream=None,
                 every: int | None = None, interval: float = 60.0):
        self.description, self.total, self.done = description, total, initial
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.every = every or max(1, round(total / 20))
        self.interval = interval
        self.start = self.last_line = time.monotonic()
        self.first = initial
        self.bar = None
        if enabled and _is_terminal(self.stream):
            from tqdm import tqdm

            # tqdm's default lock is a multiprocessing lock, whose helper process turns a SLURM
            # signal into resource_tracker tracebacks; a thread lock is all one bar needs
            tqdm.set_lock(threading.RLock())
            self.bar = tqdm(total=total, initial=initial, unit="ep", dynamic_ncols=True, desc=description,
                            file=self.stream)

    def update(self, **values) -> None:
        """One more episode done; ``values`` (floats or counts; None is left out) describe it."""
        self.done += 1
        shown = {k: v for k, v in values.items() if v is not None}
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix({k: f"{v:.1f}" if isinstance(v, float) else v for k, v in shown.items()})
            return
        if not self.enabled:
            return
        now = time.monotonic()
        if self.done % self.every and self.done != self.total and now - self.last_line < self.interval:
            return
        self.last_line = now
        self.stream.write(self.line(shown, now) + "\n")
        self.stream.flush()

    def line(self, values: dict, now: float) -> str:
        parts = [f"episode {self.done}/{self.total} ({100 * self.done // max(self.total, 1)}%)"]
        parts += [f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}" for k, v in values.items()]
        elapsed = now - self.start
        parts.append(f"{_clock(elapsed)} elapsed")
        if self.first < self.done < self.total:
            parts.append(f"~{_clock(elapsed / (self.done - self.first) * (self.total - self.done))} left")
        return f"{self.description}: " + ", ".join(parts)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _is_terminal(stream) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False
