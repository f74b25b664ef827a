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
  tests/fault_server.py), again and again until it has finished;
- ``special``: at any path a run touches, at any depth (its files, its lock, its temporaries,
  ``logs/`` and every folder and file below it, ``.hydra/``), in a fresh, a partial or a finished
  folder: a symbolic link (to a file or a folder outside), a hard link to a file outside, a FIFO,
  a folder where a file goes (or a file where a folder goes), or a device;
- ``kernel``: the compiled matrix kernel in a copy of the cache with bits flipped or cut short;
- ``pickle``: a model file whose pickle runs code when loaded (a run's ``actor.pt``, and with
  Stable-Baselines3 installed, a ``model.zip``'s settings);
- ``numerics``: a partial run resumed under other products (the first part ran without the kernels);
- ``record``: a finished run's summary rewritten and sealed again, asking for what no run records
  (networks beyond its weights or the machine, values beyond their ceilings, a final performance no
  episode totals): read as damaged, or its policy refused naming summary.json, before anything is built;
- ``copy``: a finished run's folder copied beside itself in its sweep: the report finds one run in two
  folders and names both, instead of counting it twice.

Then the same command runs again, as a user would, and the outcome is classed:

- ``refused``: a one-sentence refusal (ConfigError, RunFolderError, CheckpointError, DiskFull) that
  names the file, with the folder's files left as they were (and nothing written through a link);
- ``exact``: the run finished with the reference's metrics.csv, actor.pt and critic.pt, byte for byte;
- ``unchanged``: a finished run whose fault changed no value (a flip of ``e`` to ``E`` in a number);
- ``escaped``: a file outside the folder changed, or code in a file ran. Must be 0;
- ``hung``: the run blocked (60 s without an end). Must be 0;
- ``misreported``: anything else: a run that finished with other bytes, a damaged folder taken for a
  finished one, or any other exception. Must be 0.
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import random
import shutil
import signal
import stat
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
CLEAR = (ConfigError, outputs.FileRefused, CheckpointError)  # FileRefused: the file door's, RunFolderError among them


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
    found = {}
    for here, _, names in os.walk(folder):  # links not followed
        for name in names:
            path = Path(here) / name
            if name != ".lock" and not path.is_symlink() and path.is_file():
                found[str(path.relative_to(folder))] = path.read_bytes()
    return found


from tests.test_files import Hung, no_hang as deadline  # noqa: E402


# Where a run reads or writes (relative to its folder), and whether a folder or a file belongs there.
SPECIAL_PLACES = {"summary.json": "file", "metrics.csv": "file", "actor.pt": "file", "critic.pt": "file",
                  "checkpoint.pt": "file", ".lock": "file", "summary.json.tmp": "file", "metrics.csv.tmp": "file",
                  "logs": "folder", "logs/scalars": "folder", "logs/scalars/train": "folder",
                  "logs/scalars/train/total_reward.csv": "file", ".hydra": "folder", ".hydra/config.yaml": "file"}
SPECIAL_KINDS = ("symlink", "hardlink", "fifo", "folder", "device")
VICTIM = b"a file outside the run folder\n"


def make_special(target: Path, kind: str, belongs: str, victim: Path) -> str:
    """Put ``kind`` at ``target`` (its folders made real); returns what was put there."""
    target.parent.mkdir(parents=True, exist_ok=True)
    if os.path.lexists(target):
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        else:
            target.unlink()
    if kind == "hardlink" and belongs == "folder":
        kind = "symlink"
    if kind == "symlink":
        target.symlink_to(victim.parent if belongs == "folder" else victim)
    elif kind == "hardlink":
        os.link(victim, target)
    elif kind == "fifo":
        os.mkfifo(target)
    elif kind == "folder":
        if belongs == "folder":
            target.write_bytes(b"a file where a folder goes\n")
            kind = "file"
        else:
            target.mkdir()
    elif os.geteuid() == 0:
        os.mknod(target, stat.S_IFCHR | 0o666, os.makedev(1, 3))
    else:
        target.symlink_to("/dev/null")
        kind = "link to a device"
    return kind


def try_special(trial: Trial, rng: random.Random, folder: Path) -> tuple[str, str]:
    """A link, hard link, FIFO, folder or device where a run reads or writes, at any depth; then the same command."""
    source = rng.choice(("fresh", "partial", "reference"))
    place = rng.choice(sorted(SPECIAL_PLACES))
    if source == "fresh":
        folder.mkdir(parents=True)
    else:
        shutil.copytree(getattr(trial, source), folder, symlinks=True)
    victims = folder.parent / f"{folder.name}.outside"
    victims.mkdir()
    victim = victims / "victim.txt"
    victim.write_bytes(VICTIM)
    target = folder / place
    kind = make_special(target, rng.choice(SPECIAL_KINDS), SPECIAL_PLACES[place], victim)
    label = f"special {source}/{place}: {kind}"
    before = snapshot(folder)
    try:
        with deadline(60):
            summary = trial.train(folder, [*trial.overrides, "logger=csv"])
    except Hung:
        return "hung", label
    except CLEAR as err:
        if victim.read_bytes() != VICTIM or sorted(p.name for p in victims.iterdir()) != ["victim.txt"]:
            return "escaped", f"{label}: refused, but a file outside the folder changed"
        if snapshot(folder) != before:
            return "misreported", f"{label}: refused ({err}) but the folder changed"
        if str(target) not in str(err) and target.name not in str(err):
            return "misreported", f"{label}: refused without naming {target}: {err}"
        return "refused", label
    except Exception as err:  # noqa: BLE001 (any other ending is a failure of the guarantee)
        return "misreported", f"{label}: {type(err).__name__}: {err}"
    finally:
        escaped = victim.read_bytes() != VICTIM or sorted(p.name for p in victims.iterdir()) != ["victim.txt"]
    if escaped:
        return "escaped", f"{label}: a file outside the folder changed"
    if not trial.exact(folder) or summary["status"] != "completed":
        return "misreported", f"{label}: finished with other results"
    return ("unchanged" if source == "reference" else "exact"), label


def try_kernel(rng: random.Random, work: Path) -> tuple[str, str]:
    """The compiled kernel in a copy of the cache damaged (bits flipped, or cut short): it must be
    rebuilt, with a warning, never loaded, and the rebuilt library must be the one built before."""
    import warnings

    from learners import kernels

    if kernels._compiler() is None:
        return "unchanged", "kernel: no compiler here (nothing is cached)"
    saved = os.environ.get("RACING_KERNEL_CACHE")
    cache = work / f"cache-{rng.randrange(1 << 30)}"
    try:
        os.environ["RACING_KERNEL_CACHE"] = str(cache)
        path, digest = kernels._build()
        good = path.read_bytes()
        if rng.random() < 0.5:
            data = bytearray(good)
            for _ in range(rng.choice((1, 10, 200))):
                data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
            detail = "bits flipped"
        else:
            data = good[:rng.randrange(len(good))]
            detail = "cut short"
        path.write_bytes(bytes(data))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            again, again_digest = kernels._build()
        warned = any("rebuilt, not loaded" in str(w.message) for w in caught)
        if bytes(data) == good:
            return "unchanged", f"kernel: {detail} (no byte changed)"
        if again_digest != digest or path.read_bytes() != good or not warned:
            return "misreported", f"kernel: {detail}: not rebuilt to the library built before (warned: {warned})"
        return "refused", f"kernel: {detail}"
    finally:
        if saved is None:
            os.environ.pop("RACING_KERNEL_CACHE", None)
        else:
            os.environ["RACING_KERNEL_CACHE"] = saved
        shutil.rmtree(cache, ignore_errors=True)


class _Marker:
    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return (Path.touch, (Path(self.path),))


def try_pickle(trial: Trial, rng: random.Random, folder: Path) -> tuple[str, str]:
    """A finished run whose weights file carries a pickle that runs code when unpickled."""
    import pickle

    import torch

    from engine.evaluation import load_policy

    shutil.copytree(trial.reference, folder, symlinks=True)
    marker = folder.parent / f"{folder.name}.marker"
    name = rng.choice(("actor.pt", "critic.pt"))
    payload = {"weight": torch.zeros(1), "hook": _Marker(str(marker))}
    with open(folder / name, "wb") as f:
        torch.save(payload, f, pickle_module=pickle)
    label = f"pickle {name}"
    try:
        load_policy(folder)
        trial.train(folder)
    except CLEAR + (ValueError,) as err:
        if marker.exists():
            return "escaped", f"{label}: its code ran"
        return ("refused", label) if name in str(err) else ("misreported", f"{label}: refused without naming it: {err}")
    except Exception as err:  # noqa: BLE001
        return ("escaped" if marker.exists() else "misreported"), f"{label}: {type(err).__name__}: {err}"
    return ("escaped" if marker.exists() else "misreported"), f"{label}: loaded"


def try_numerics(trial: Trial, rng: random.Random, folder: Path) -> tuple[str, str]:
    """A partial run made without the kernels (portable products), resumed with them: refused."""
    from learners import kernels

    import warnings

    real = kernels._load
    kernels._load = lambda: (None, "no compiler (fault injection)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the fallback's own warning: the point of this fault
            numerics.apply(numerics.DEFAULT)
        with stopped_after(rng.randint(2, 4)):  # a checkpoint after one episode at least
            trial.train(folder)
    finally:
        kernels._load = real
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            numerics.apply(numerics.DEFAULT)
    label = "numerics: resumed with the kernels after a part without them"
    if kernels.unavailable_reason() is not None:
        return "unchanged", "numerics: no kernels here, one products throughout"
    try:
        trial.train(folder)
    except ConfigError as err:
        return ("refused", label) if "resume_numerics=any" in str(err) else ("misreported", f"{label}: {err}")
    except Exception as err:  # noqa: BLE001
        return "misreported", f"{label}: {type(err).__name__}: {err}"
    return "misreported", f"{label}: resumed silently"


# A finished run's summary rewritten and sealed again (the seal guards damage, not forgery): values no run could
# record, or sizes its weights do not hold. Every tool must refuse the run before building anything from them.
RECORD_EDITS = (
    (("settings", "network", "actor_hidden"), [65536] * 64),  # each layer within its ceiling: 1.1 TB in all
    (("settings", "network", "actor_hidden"), [2048, 2048]),  # more than actor.pt holds
    (("settings", "network", "actor_hidden"), [10**9]),
    (("settings", "env", "options", "max_steps"), 10**9),
    (("settings", "env", "past_steps"), -1),
    (("settings", "algo", "minibatch_size"), 10**12),
    (("settings", "algo", "loss"), "no_such_learner"),
    (("settings", "numerics"), "x" * 10_000),
    (("final_mean",), float("nan")),
    (("final_mean",), 1e300),
    (("episodes",), -5),
    (("seed",), "2067791"),
)


def try_record(trial: Trial, rng: random.Random, folder: Path) -> tuple[str, str]:
    """A finished run whose resealed summary asks for what no run records: the folder reads as damaged, or
    loading its policy is refused naming summary.json, before any network is built."""
    from engine.evaluation import load_policy

    shutil.copytree(trial.reference, folder, symlinks=True)
    path, value = rng.choice(RECORD_EDITS)
    summary = _summary_values(folder)
    node = summary
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    (folder / "summary.json").write_text(json.dumps(outputs.seal(summary)))
    label = f"record {'.'.join(path)}={str(value)[:30]}"
    if rundir.state(folder).kind == "damaged":
        return "refused", label
    try:
        load_policy(folder)
    except CLEAR as err:
        return ("refused", label) if "summary.json" in str(err) else ("misreported", f"{label}: {err}")
    except Exception as err:  # noqa: BLE001
        return "misreported", f"{label}: {type(err).__name__}: {err}"
    return "misreported", f"{label}: loaded"


def try_copy(trial: Trial, rng: random.Random, folder: Path) -> tuple[str, str]:
    """A finished run's folder copied beside it, or into another folder of the sweep (a backup): the report
    counts it once and names the copy in one line (engine.runset), not as two runs."""
    from engine.runset import read_runs

    sweep = folder / "sweep"
    original = sweep / "spg" / "recent" / "seed2067791"
    shutil.copytree(trial.reference, original, symlinks=True)
    name = rng.choice(("seed2067791-backup", "old/seed2067791", "seed2067791 copy", "../recent-2/seed2067791"))
    copy = original.parent / name
    shutil.copytree(trial.reference, copy, symlinks=True)
    label = f"copy {name}"
    found = read_runs([sweep])
    if len(found.runs) == 1 and len(found.notes) == 1 and "counted once" in found.notes[0]:
        return "refused", label
    return "misreported", f"{label}: runs {found.runs}, notes {found.notes}"


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
        every = list(dict.fromkeys(KINDS))  # each kind once first, so that a small sample tries them all
        for i in range(trials):
            kind = every[i] if i < len(every) else rng.choice(KINDS)
            folder = base / f"t{i}"
            if kind == "disk":
                outcome, label = try_disk_full(trial, rng, folder, writes)
            elif kind == "special":
                outcome, label = try_special(trial, rng, folder)
            elif kind == "kernel":
                outcome, label = try_kernel(rng, base)
            elif kind == "pickle":
                outcome, label = try_pickle(trial, rng, folder)
            elif kind == "numerics":
                outcome, label = try_numerics(trial, rng, folder)
            elif kind == "record":
                outcome, label = try_record(trial, rng, folder)
            elif kind == "copy":
                outcome, label = try_copy(trial, rng, folder)
            else:
                outcome, label = try_file_fault(trial, kind, rng, folder)
            counts[(family, kind, outcome)] += 1
            if outcome in BAD:
                failures.append(f"{family}: {outcome}: {label}")
            for leftover in (folder, base / f"t{i}.outside"):
                if leftover.is_dir() and not leftover.is_symlink():
                    shutil.rmtree(leftover, ignore_errors=True)
        if signals:
            for outcome, label in try_signals(family, base, rng, signals, signal_episodes):
                counts[(family, "signal", outcome)] += 1
                if outcome in BAD:
                    failures.append(f"{family}: {label}")
    return counts, failures


OUTCOMES = ("refused", "exact", "unchanged", "misreported", "escaped", "hung")
BAD = ("misreported", "escaped", "hung")
# faults drawn per trial (flips twice as often: they reach every byte)
KINDS = ("flip", "flip", "truncate", "link", "disk", "special", "special", "kernel", "pickle", "numerics", "record",
         "copy")


def table(counts: Counter) -> str:
    kinds = sorted({(f, k) for f, k, _ in counts})
    lines = ["| family | fault | tried | " + " | ".join(OUTCOMES) + " |", "|---|---|" + "---:|" * (len(OUTCOMES) + 1)]
    for family, kind in kinds:
        row = {o: counts[(family, kind, o)] for o in OUTCOMES}
        lines.append(f"| {family} | {kind} | {sum(row.values())} | " + " | ".join(str(row[o]) for o in OUTCOMES) + " |")
    total = {o: sum(v for (_, _, out), v in counts.items() if out == o) for o in OUTCOMES}
    lines.append(f"| all | all | {sum(total.values())} | " + " | ".join(str(total[o]) for o in OUTCOMES) + " |")
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
