"""Fault injection on run folders: every fault is refused clearly or survived exactly, never misreported.

    python -m tests.fault_injection --trials 400 --signals 12     # the large sample (docs/guarantees.md)

CI runs a small sample (tests/test_fault_injection.py). For each learner family (the paper's SPG, the
off-policy SAC, each a tiny run checkpointed every episode) it makes a reference run, uninterrupted,
and a partial run (stopped with a checkpoint), then tries faults drawn at random:

- ``flip``: one bit flipped at a random offset of a finished run's file (summary.json, metrics.csv,
  actor.pt, critic.pt) or of a partial run's (checkpoint.pt, metrics.csv), or of the track file a
  run trained on;
- ``truncate``: the same files cut at a random length;
- ``link``: a run file (or its .lock) replaced by a symbolic link to a file outside the folder;
- ``disk``: the disk full at the n-th write of a fresh run (every file write and fsync counts);
- ``signal``: SIGKILL, SIGTERM or SIGINT at a random moment of a run (a forked session of
  tests/fault_server.py), again and again until it has finished.

Then the same command runs again, as a user would, and the outcome is classed:

- ``refused``: a one-sentence refusal (ConfigError, RunFolderError, CheckpointError, DiskFull) that
  names the file, with the folder's files left as they were (and nothing written through a link);
- ``exact``: the run finished with the reference's metrics.csv, actor.pt and critic.pt, byte for byte;
- ``unchanged``: a finished run whose fault changed no value (a flip of ``e`` to ``E`` in a number);
- ``misreported``: anything else: a run that finished with other bytes, a damaged folder taken for a
  finished one, a file outside the folder changed, or any other exception. Must be 0.
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import random
import shutil
import signal
import sys
import tempfile
from collections import Counter
from contextlib import contextmanager
from pathlib import Path

os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")  # torchrl's INFO lines (set before it loads)

from engine import numerics  # noqa: E402

numerics.apply(numerics.DEFAULT)  # before torch loads, as train.py does

from engine import outputs, rundir  # noqa: E402 (after the numerics)
from engine.checkpoint import CheckpointError  # noqa: E402
from engine.config import ConfigError, RunConfig  # noqa: E402
from engine.runner import train_population  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
COMMON = ["episodes=5", "checkpoint_every=1", "env.options.max_steps=40", "final_window=3", "progress=false",
          "logger=none"]
FAMILIES = {
    "spg": ["algo=spg", "er=hybrid", "algo.minibatch_size=40", *COMMON],
    "sac": ["algo=sac", "er=memory", "algo.td.warmup_episodes=1", "algo.td.updates_per_step=0.1",
            "algo.minibatch_size=32", *COMMON],
}
RESULT_FILES = ("metrics.csv", "actor.pt", "critic.pt")
FINISHED_FILES = ("summary.json", *RESULT_FILES)
PARTIAL_FILES = ("checkpoint.pt", "metrics.csv")
CLEAR = (ConfigError, outputs.RunFolderError, CheckpointError)


class Trial:
    """The folders of one family: its settings, reference run, partial run and a run on a track file."""

    def __init__(self, family: str, work: Path):
        self.family, self.work = family, work
        self.overrides = FAMILIES[family]
        self.settings = RunConfig.compose_mapping(*self.overrides)
        self.reference = work / "reference"
        self.train(self.reference)
        self.partial = work / "partial"
        with stopped_after(2):
            self.train(self.partial)
        shutil.copy(ROOT / "racing" / "tracks" / "oval.csv", work / "oval.csv")

    def train(self, folder: Path, overrides: list[str] | None = None) -> dict:
        settings = self.settings if overrides is None else RunConfig.compose_mapping(*overrides)
        return train_population(RunConfig.from_mapping(settings), folder, settings)[0]

    def exact(self, folder: Path) -> bool:
        return all((folder / n).read_bytes() == (self.reference / n).read_bytes() for n in RESULT_FILES)


@contextmanager
def stopped_after(episodes: int):
    """A run within the block stops (KeyboardInterrupt) once it has written ``episodes`` rows."""
    original = outputs.MetricsWriter.write

    def write(self, row):
        original(self, row)
        if row["episode"] == episodes - 1:
            raise KeyboardInterrupt

    outputs.MetricsWriter.write = write
    try:
        yield
    except KeyboardInterrupt:
        pass
    finally:
        outputs.MetricsWriter.write = original


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not p.is_symlink() and p.name != ".lock"}


def flip(path: Path, rng: random.Random) -> str:
    data = bytearray(path.read_bytes())
    offset = rng.randrange(len(data))
    data[offset] ^= 1 << rng.randrange(8)
    path.write_bytes(bytes(data))
    return f"bit flipped at byte {offset} of {len(data)}"


def truncate(path: Path, rng: random.Random) -> str:
    size = path.stat().st_size
    cut = rng.randrange(size)
    with open(path, "r+b") as f:
        f.truncate(cut)
    return f"cut to {cut} of {size} bytes"


def _summary_values(folder: Path) -> dict:
    data = json.loads((folder / "summary.json").read_text())
    return {k: v for k, v in data.items() if k != outputs.DIGEST_KEY}


def try_file_fault(trial: Trial, kind: str, rng: random.Random, folder: Path) -> tuple[str, str]:
    """A flip, truncation or link in a copy of the finished, partial or track-file run; then the same command."""
    source, name = rng.choice([("reference", n) for n in FINISHED_FILES] + [("partial", n) for n in PARTIAL_FILES]
                              + [("on_track", "track")] + ([("partial", ".lock")] if kind == "link" else []))
    overrides = None
    if source == "on_track":  # a partial run on a copy of the track file of its own, outside the folder
        target = folder.parent / f"{folder.name}.csv"
        shutil.copy(trial.work / "oval.csv", target)
        overrides = [*trial.overrides, "env.track=file", f"env.track_file={target}"]
        with stopped_after(2):
            trial.train(folder, overrides)
    else:
        shutil.copytree(getattr(trial, source), folder, symlinks=True)
        target = folder / name
    victim = folder.parent / f"{folder.name}.victim"
    if kind == "link":
        victim.write_bytes(b"a file outside the run folder\n")
        target.unlink(missing_ok=True)
        target.symlink_to(victim)
        detail = "replaced by a link"
    elif kind == "flip":
        detail = flip(target, rng)
    else:
        detail = truncate(target, rng)
    label = f"{kind} {source}/{target.name}: {detail}"
    before = snapshot(folder)
    was = rundir.state(folder)
    try:
        summary = trial.train(folder, overrides)
    except CLEAR as err:
        if victim.exists() and victim.read_bytes() != b"a file outside the run folder\n":
            return "misreported", f"{label}: the linked file was written through"
        if snapshot(folder) != before:
            return "misreported", f"{label}: refused ({err}) but the folder changed"
        if target.name not in str(err):
            return "misreported", f"{label}: refused without naming {target.name}: {err}"
        return "refused", label
    except Exception as err:  # noqa: BLE001 (any other ending is a failure of the guarantee)
        return "misreported", f"{label}: {type(err).__name__}: {err}"
    if source == "reference":  # taken for finished: only if nothing that counts changed
        if was.kind != "finished" or _summary_values(folder) != _summary_values(trial.reference) \
                or not trial.exact(folder):
            return "misreported", f"{label}: taken for a finished run ({was.kind}) with other content"
        return "unchanged", label
    if source == "on_track":
        return "misreported", f"{label}: resumed on a changed track file"
    if not trial.exact(folder) or summary["status"] != "completed":
        return "misreported", f"{label}: resumed to other results"
    return "exact", label


@contextmanager
def writes_failing_at(nth: int | None):
    """Within the block, every write of a run (an fsync, a row appended) is counted, and the ``nth``
    fails for want of space (a row half written, an fsync raising ENOSPC); yields the count so far."""
    seen = [0]
    real_fsync, real_append = os.fsync, outputs.MetricsWriter.append

    def fsync(fd):
        seen[0] += 1
        if seen[0] == nth:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_fsync(fd)

    def append(self, data):
        seen[0] += 1
        if seen[0] != nth:
            return real_append(self, data)
        real_write = os.write
        os.write = lambda fd, chunk: real_write(fd, chunk[:len(chunk) // 2])
        try:
            return real_append(self, data)
        finally:
            os.write = real_write

    os.fsync, outputs.MetricsWriter.append = fsync, append
    try:
        yield seen
    finally:
        os.fsync, outputs.MetricsWriter.append = real_fsync, real_append


def try_disk_full(trial: Trial, rng: random.Random, folder: Path, writes: int) -> tuple[str, str]:
    """The n-th write (file write or fsync) of a fresh run fails for want of space; then the same command."""
    nth = rng.randint(1, writes)
    label = f"disk full at write {nth} of {writes}"
    failed = None
    try:
        with writes_failing_at(nth):
            trial.train(folder)
    except outputs.DiskFull as err:
        failed = err
    except Exception as err:  # noqa: BLE001
        return "misreported", f"{label}: {type(err).__name__}: {err}"
    if list(folder.glob("*.tmp")):
        return "misreported", f"{label}: a temporary file was left"
    if failed is not None:
        try:
            trial.train(folder)
        except Exception as err:  # noqa: BLE001
            return "misreported", f"{label}: the rerun failed: {type(err).__name__}: {err}"
    if not trial.exact(folder):
        return "misreported", f"{label}: ended with other results"
    return ("exact" if failed is not None else "unchanged"), label


def count_writes(trial: Trial, folder: Path) -> int:
    with writes_failing_at(None) as seen:
        trial.train(folder)
    return seen[0]


def try_signals(family: str, work: Path, rng: random.Random, kills: int, episodes: int = 150) -> list[tuple[str, str]]:
    """``kills`` signals at random moments of one run (forked sessions), then to its end; the result
    must be the uninterrupted run's."""
    from tests.test_run_folders import FaultServer

    longer = [o if not o.startswith("episodes=") else f"episodes={episodes}" for o in FAMILIES[family]]  # moments
    server = FaultServer(work / "sessions.log", longer)
    outcomes = []
    try:
        reference, run = work / "signal_reference", work / "signal_run"
        assert server.session(reference) == 0
        for i in range(kills):
            if (run / "summary.json").exists():
                break
            name = rng.choice(("SIGKILL", "SIGTERM", "SIGINT"))
            status = server.session(run, kill_after=(rng.uniform(0.1, 1.5), name))
            state = rundir.state(run).kind
            ok = state in ("empty", "resumable", "finished") and status in (0, 130, 143, -signal.SIGKILL)
            outcomes.append(("exact" if ok else "misreported", f"signal {name}: status {status}, folder {state}"))
        final = server.session(run)
        same = final == 0 and all((run / n).read_bytes() == (reference / n).read_bytes() for n in RESULT_FILES)
        if not same:
            outcomes = [("misreported", f"{label}: the resumed run ended with other results (status {final})")
                        for _, label in outcomes]
    finally:
        server.close()
    log = (work / "sessions.log").read_text()
    if "Traceback" in log:
        outcomes.append(("misreported", "a session ended in a traceback: " + log[-500:]))
    return outcomes


def run(trials: int, signals: int, seed: int, families: list[str], work: Path,
        signal_episodes: int = 150) -> tuple[Counter, list[str]]:
    rng = random.Random(seed)
    counts: Counter = Counter()
    failures: list[str] = []
    for family in families:
        base = work / family
        trial = Trial(family, base)
        writes = count_writes(trial, base / "count")
        for i in range(trials):
            kind = rng.choice(("flip", "flip", "truncate", "link", "disk"))
            folder = base / f"t{i}"
            outcome, label = (try_disk_full(trial, rng, folder, writes) if kind == "disk"
                              else try_file_fault(trial, kind, rng, folder))
            counts[(family, kind, outcome)] += 1
            if outcome == "misreported":
                failures.append(f"{family}: {label}")
            shutil.rmtree(folder, ignore_errors=True)
        if signals:
            for outcome, label in try_signals(family, base, rng, signals, signal_episodes):
                counts[(family, "signal", outcome)] += 1
                if outcome == "misreported":
                    failures.append(f"{family}: {label}")
    return counts, failures


def table(counts: Counter) -> str:
    kinds = sorted({(f, k) for f, k, _ in counts})
    lines = ["| family | fault | tried | refused | exact | unchanged | misreported |", "|---|---|---:|---:|---:|---:|---:|"]
    for family, kind in kinds:
        row = {o: counts[(family, kind, o)] for o in ("refused", "exact", "unchanged", "misreported")}
        lines.append(f"| {family} | {kind} | {sum(row.values())} | {row['refused']} | {row['exact']} | "
                     f"{row['unchanged']} | {row['misreported']} |")
    total = sum(counts.values())
    lost = sum(v for (_, _, o), v in counts.items() if o == "misreported")
    lines.append(f"| all | all | {total} | | | | {lost} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=200, help="file and disk faults per family")
    parser.add_argument("--signals", type=int, default=12, help="signals at random moments per family")
    parser.add_argument("--seed", type=int, default=20261205)
    parser.add_argument("--families", default=",".join(FAMILIES), help=f"of {', '.join(FAMILIES)}")
    args = parser.parse_args(argv)
    families = args.families.split(",")
    unknown = [f for f in families if f not in FAMILIES]
    if unknown:
        parser.error(f"unknown families {unknown}; choose from {', '.join(FAMILIES)}")
    with tempfile.TemporaryDirectory(prefix="faults-") as work:
        counts, failures = run(args.trials, args.signals, args.seed, families, Path(work))
    print(table(counts))
    for line in failures:
        print(f"MISREPORTED {line}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
