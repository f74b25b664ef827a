"""What a hostile user tried (issue 64), each case end to end: no input a tool reads can run code,
hang it, make it lie, or make it write elsewhere. Each test names the class and the case it holds
against; the rules themselves are tested once in tests/test_files.py."""

from __future__ import annotations

import base64
import json
import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from engine import rundir
from engine.outputs import seal
from tests.test_run_folders import TINY, train
from tests.test_train import ENV, ROOT

CHECKPOINTED = [*TINY, "checkpoint_every=1"]


def run(script: str, *args: str, env: dict | None = None, timeout: int = 300):
    from tests import zygote

    return zygote.run([ROOT / script, *args], cwd=ROOT, env=env or ENV, timeout=timeout)


def one_line(result) -> str:
    """The tool's stderr, which must be one line (warnings aside), without a traceback."""
    lines = [line for line in result.stderr.splitlines() if line.strip() and "Warning" not in line
             and not line.startswith(("  warnings.warn", "Note: "))]
    assert "Traceback" not in result.stderr, result.stderr[-3000:]
    assert len(lines) == 1, result.stderr[-3000:]
    return lines[0]


# ------------------------------------------------------------------ code runs from a file a tool reads

class Payload:
    """Unpickled, it writes a marker file: the proof that loading ran the file's code."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (Path.touch, (Path(self.marker),))


def sb3_zip(folder: Path, payload_in: str | None, marker: Path) -> Path:
    """A Stable-Baselines3 SAC model.zip; ``payload_in``: the ``data`` entry whose ``:serialized:``
    (cloudpickle, which SB3's own ``load`` unpickles) carries ``Payload``."""
    import zipfile

    import cloudpickle
    import gymnasium as gym
    import stable_baselines3

    import racing

    path = folder / "model.zip"
    stable_baselines3.SAC("MlpPolicy", gym.make(racing.ENV_ID, track_seed=1), seed=0, device="cpu").save(path)
    if payload_in is None:
        return path
    with zipfile.ZipFile(path) as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    data = json.loads(entries["data"])
    data[payload_in] = {":type:": "<class 'x'>", ":serialized:": base64.b64encode(cloudpickle.dumps(Payload(marker))).decode()}
    entries["data"] = json.dumps(data).encode()
    with zipfile.ZipFile(path, "w") as archive:
        for name, content in entries.items():
            archive.writestr(name, content)
    return path


@pytest.mark.slow
def test_a_downloaded_sb3_model_never_runs_its_code_when_scored_or_filmed(tmp_path):
    """Class: code runs from a file. On 6b09ff3 SB3's load unpickled the zip's settings first."""
    pytest.importorskip("stable_baselines3")
    marker = tmp_path / "marker"
    schedule = sb3_zip(tmp_path, "lr_schedule", marker)  # a setting SB3 unpickles and a policy never needs
    scored = run("score.py", str(schedule), "--tracks", "1001", "--episodes", "1")
    assert scored.returncode == 0 and "Stable-Baselines3 SAC" in scored.stdout, scored.stderr[-2000:]
    filmed = run("evaluate.py", str(schedule), "--video", str(tmp_path / "x.gif"))
    assert filmed.returncode == 0, filmed.stderr[-2000:]
    (tmp_path / "policy").mkdir()
    needed = sb3_zip(tmp_path / "policy", "policy_kwargs", marker)  # a setting the policy would need: refused
    refused = run("score.py", str(needed))
    assert refused.returncode == 2
    assert "need unpickling" in one_line(refused) and str(needed) in one_line(refused)
    assert not marker.exists()


@pytest.mark.slow
def test_a_damaged_sb3_run_folder_is_not_scored(tmp_path):
    """Class: results that lie. rundir calls it damaged; on 6b09ff3 score.py scored it all the same."""
    pytest.importorskip("stable_baselines3")
    from engine.outputs import file_record, write_summary

    folder = tmp_path / "sb3_sac" / "default" / "seed1"
    folder.mkdir(parents=True)
    sb3_zip(folder, None, tmp_path / "marker")
    (folder / "metrics.csv").write_text("episode,total_reward,crashes,final_checkpoint\n0,1.0,0,3\n")
    write_summary(folder, {"algo": "sb3_sac", "er": "default", "seed": 1, "status": "completed", "final_mean": 1.0,
                           "episodes": 1, "settings": {}, "code": {"commit": "0" * 40},
                           "files": file_record(folder, ("metrics.csv", "model.zip"))})
    assert rundir.state(folder).kind == "finished"
    with open(folder / "model.zip", "ab") as f:
        f.write(b"\0")
    result = run("score.py", str(folder))
    assert result.returncode == 2 and "differs from the file its summary records" in one_line(result) or \
        "is not the file its summary records" in one_line(result)


# ------------------------------------------------------------------ writes outside the run folder

@pytest.mark.slow
def test_a_lock_that_is_a_hard_link_is_refused_and_its_other_file_untouched(tmp_path):
    outside = tmp_path / "thesis.tex"
    outside.write_text("chapter one\n")
    folder = tmp_path / "run"
    folder.mkdir()
    os.link(outside, folder / ".lock")
    result = run("train.py", *TINY, f"hydra.run.dir={folder}")
    assert result.returncode == 2 and "2 names (a hard link)" in one_line(result)
    assert outside.read_text() == "chapter one\n" and sorted(p.name for p in folder.iterdir()) == [".lock"]


@pytest.mark.parametrize("where", ["logs/scalars/train/total_reward.csv", "logs/scalars", ".hydra/config.yaml"])
def test_a_link_below_a_folder_the_run_writes_into_is_refused(tmp_path, where):
    """TorchRL's CSV logger opens its files itself: on 6b09ff3 it appended 20 rows through the link."""
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "total_reward.csv").write_text("mine\n")
    folder = tmp_path / "run"
    link = folder / where
    link.parent.mkdir(parents=True)
    link.symlink_to(outside / "total_reward.csv" if where.endswith((".csv", ".yaml")) else outside)
    for overwrite in ("overwrite=false", "overwrite=true"):
        result = run("train.py", *TINY, "logger=csv", overwrite, f"hydra.run.dir={folder}")
        assert result.returncode == 2 and str(link) in one_line(result), result.stderr[-2000:]
        assert (outside / "total_reward.csv").read_text() == "mine\n" and link.is_symlink()
    assert not (folder / "metrics.csv").exists()


def test_a_member_folder_that_is_a_link_is_never_written_through_or_cleared(tmp_path):
    """On 6b09ff3, overwrite=true deleted the files of the folder the member's link pointed to."""
    mine = tmp_path / "my_folder"
    (mine / "logs").mkdir(parents=True)
    (mine / "logs" / "draft.tex").write_text("a thesis draft\n")
    (mine / "metrics.csv").write_text("my own numbers\n")
    population = tmp_path / "population"
    population.mkdir()
    (population / "seed7").symlink_to(mine)
    before = {p: p.read_bytes() for p in mine.rglob("*") if p.is_file()}
    for overwrite in ("overwrite=false", "overwrite=true"):
        result = run("train.py", *TINY, "seeds=[6,7]", overwrite, f"hydra.run.dir={population}")
        assert result.returncode == 2 and "seed7 is a symbolic link" in one_line(result)
        assert {p: p.read_bytes() for p in mine.rglob("*") if p.is_file()} == before
    assert not (population / "seed6").exists() or not any((population / "seed6").iterdir())


def test_no_tool_writes_into_a_run_folder_whatever_its_state(tmp_path):
    """On 258b7c4 ``evaluate.py RUN --table POP/.hydra/config.yaml`` replaced a finished population's resolved
    configuration (its top folder holds .hydra/ and .lock, its members the summaries), and ``--table
    RUN/metrics.csv`` while RUN trained (before its first checkpoint) exited 0: tools knew a run folder only
    by a summary or a checkpoint. One rule (engine.rundir.run_folder_of) now answers for every tool."""
    population = tmp_path / "population"
    done = run("train.py", *TINY, "seeds=[6,7]", f"hydra.run.dir={population}")
    assert done.returncode == 0, done.stderr[-2000:]
    config = population / ".hydra" / "config.yaml"
    before = config.read_bytes()
    training = tmp_path / "training"  # a run between its start and its first checkpoint: rows and a lock
    training.mkdir()
    (training / "metrics.csv").write_text("episode,total_reward\n0,1.0\n")
    (training / ".lock").write_text("")
    (tmp_path / ".lock").write_text("")  # another program's lock (pytest's numbered folders have one): no run
    for target in (config, training / "metrics.csv", population / "notes.csv"):
        result = run("evaluate.py", str(population / "seed6"), "--episodes", "1", "--table", str(target))
        last = result.stderr.strip().splitlines()[-1]  # argparse: its usage, then the one line
        assert result.returncode == 2 and "is inside the run folder" in last and "Traceback" not in result.stderr, \
            result.stderr[-2000:]
    assert config.read_bytes() == before and (training / "metrics.csv").read_text() == "episode,total_reward\n0,1.0\n"
    assert not (population / "notes.csv").exists()


def test_a_row_edited_while_the_run_trains_is_never_sealed_as_its_own(tmp_path, monkeypatch):
    """On 258b7c4 a metrics.csv row edited while the run trained was sealed into the finished run as its own:
    a run seals what it wrote (a running digest of its rows), so an edit behind its back is damage."""
    from engine import run_context
    from engine.outputs import RunFolderError

    original = run_context.RunContext.log

    def log(self, episode, batch, totals):
        original(self, episode, batch, totals)
        if episode == 1:  # someone "fixes" the first episode's reward while the run goes on
            path = self.members[0].folder / "metrics.csv"
            lines = path.read_text().splitlines(keepends=True)
            fields = lines[1].split(",")
            lines[1] = ",".join([fields[0], "999.0", *fields[2:]])
            path.write_text("".join(lines))

    monkeypatch.setattr(run_context.RunContext, "log", log)
    folder = tmp_path / "run"
    with pytest.raises(RunFolderError, match="changed while the run trained"):
        train(TINY, folder)
    assert not (folder / "summary.json").exists() and "999.0" in (folder / "metrics.csv").read_text()


def test_hydras_rerun_flag_never_unpickles_a_file(tmp_path):
    """On 258b7c4 ``train.py --experimental-rerun FILE`` unpickled FILE (its payload ran), then ended in a
    traceback: refused in one line, the file never read."""
    import pickle

    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    payload = tmp_path / "config.pickle"
    payload.write_bytes(pickle.dumps(Payload()))
    result = run("train.py", "--exp", str(payload))  # 35048d1: any unique prefix, which Hydra's argparse accepts, ran it
    assert result.returncode == 2 and "--experimental-rerun loads a pickled" in one_line(result), result.stderr
    assert not marker.exists()


@pytest.mark.parametrize("form", [["--experimental-rerun", "x"], ["--experimental-rerun=x"], ["--exp", "x"], ["--e=x"],
                                  ["algo=sac", "--experimental", "x", "seed=2"]])
def test_every_spelling_hydras_parser_takes_for_its_rerun_flag_is_found(form):
    from engine.command import pickle_flag

    assert pickle_flag(form) == "--experimental-rerun"
    assert pickle_flag([a for a in form if "x" not in a and "exp" not in a and a != "--e=x"]) is None


def test_a_seed_that_is_a_path_makes_no_folder_anywhere(tmp_path):
    """On 258b7c4 ``seed=/../../../../x/esc`` was refused, but only after Hydra had made ``x/esc`` outside
    outputs/ (the seed formed the folder's last part unchecked)."""
    import shutil

    escaped = ROOT / f"escaped-{tmp_path.name}"
    try:
        result = run("train.py", *TINY, f"seed=/../../../../{escaped.name}/esc")
        assert result.returncode != 0 and "seed must be a name" in one_line(result), result.stderr[-2000:]
        assert not escaped.exists()
    finally:
        if escaped.exists():
            shutil.rmtree(escaped)


def test_a_configuration_value_never_makes_a_folder_outside(tmp_path):
    result = run("train.py", "-m", *TINY, "algo.name=../../../escaped", f"hydra.sweep.dir={tmp_path}/sweep",
                 "hydra/launcher=basic")
    assert result.returncode != 0 and not (tmp_path.parent / "escaped").exists()
    assert "algo.name must be a name" in result.stderr or "is not a folder inside the sweep" in result.stderr


# ------------------------------------------------------------------ hangs

@pytest.mark.parametrize("name", ["summary.json", "metrics.csv", "checkpoint.pt", "actor.pt"])
def test_a_fifo_where_a_run_file_goes_never_hangs_train(tmp_path, name):
    """On 6b09ff3 a FIFO at summary.json blocked train.py for 11 minutes."""
    folder = tmp_path / "run"
    folder.mkdir()
    os.mkfifo(folder / name)
    result = run("train.py", *TINY, f"hydra.run.dir={folder}", timeout=120)
    assert result.returncode == 2 and "FIFO" in one_line(result) and str(folder / name) in one_line(result)
    assert stat.S_ISFIFO(os.lstat(folder / name).st_mode) and not (folder / ".hydra").exists()


def test_a_fifo_where_a_temporary_goes_is_never_opened(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    os.mkfifo(folder / "summary.json.tmp")
    result = run("train.py", *TINY, f"hydra.run.dir={folder}", timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert rundir.state(folder).kind == "finished"


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("finished") / "sweep" / "spg" / "recent" / "seed2067791"
    train([*TINY], folder)
    return folder


def test_a_fifo_never_hangs_report_evaluate_or_score(tmp_path, finished):
    sweep = tmp_path / "sweep"
    shutil.copytree(finished.parent.parent.parent, sweep)
    folder = sweep / "spg" / "recent" / "seed2067791"
    (folder / "summary.json").unlink()
    os.mkfifo(folder / "summary.json")
    report = run("report.py", str(sweep), "--no-figures", timeout=120)
    assert report.returncode in (0, 2) and "FIFO" in report.stdout + report.stderr, report.stderr[-2000:]
    for script, args in (("evaluate.py", [str(folder)]), ("score.py", [str(folder)])):
        result = run(script, *args, timeout=120)
        assert result.returncode == 2 and "FIFO" in one_line(result), result.stderr[-2000:]


# ------------------------------------------------------------------ results that lie

def test_a_resume_under_other_numerics_is_refused_or_recorded_as_mixed(tmp_path, monkeypatch):
    """On 6b09ff3 a run made half with portable products (a kernel cache it could not use) and half
    with fma was sealed as fma, and its numbers were no uninterrupted run's."""
    from engine import numerics
    from engine.config import ConfigError
    from learners import kernels
    from tests.fault_injection import stopped_after

    folder = tmp_path / "run"
    monkeypatch.setattr(kernels, "_load", lambda: (None, "no compiler (a test)"))
    with pytest.warns(RuntimeWarning, match="running numerics=portable instead"):
        numerics.apply("fma")
    with stopped_after(2):
        train(CHECKPOINTED, folder)
    assert (folder / "checkpoint.pt").exists()
    monkeypatch.undo()
    numerics.apply("fma")
    with pytest.raises(ConfigError, match="computed with other numerics .*resume_numerics=any"):
        train(CHECKPOINTED, folder)
    summary = train([*CHECKPOINTED, "resume_numerics=any"], folder)
    assert summary["numerics"]["mode"] == "mixed"
    assert [(s["from_episode"], s["mode"], s["products"]) for s in summary["numerics"]["segments"]] == [
        (0, "portable", "torch"), (summary["resumed_at"], "fma", summary["numerics"]["segments"][1]["products"])]
    assert summary["numerics"]["segments"][1]["products"].startswith("fma-")


@pytest.mark.slow
def test_the_fallback_to_portable_products_is_one_plain_line(tmp_path):
    """On 258b7c4 a machine without a C++ compiler saw the fallback as a Python warning with its source line
    under it (``engine/command.py:94: RuntimeWarning: ...`` then ``numerics.apply(...)``)."""
    empty = tmp_path / "bin"
    empty.mkdir()
    (empty / "python3").symlink_to(sys.executable)
    env = {**ENV, "PATH": str(empty), "CXX": "", "RACING_KERNEL_CACHE": str(tmp_path / "cache"),
           "PYTHONWARNINGS": "default"}  # as a user's shell has it (the tests' ENV silences warnings)
    result = subprocess.run([sys.executable, "train.py", *TINY, f"hydra.run.dir={tmp_path / 'run'}"], cwd=ROOT,
                            env=env, capture_output=True, text=True, timeout=300)  # a new process: no kernel loaded
    assert result.returncode == 0, result.stderr[-2000:]
    notes = [line for line in result.stderr.splitlines() if "running numerics=portable instead" in line]
    assert len(notes) == 1 and notes[0].startswith("Warning: numerics=fma:"), result.stderr[-2000:]
    assert "numerics.apply(" not in result.stderr and "RuntimeWarning" not in result.stderr


@pytest.mark.slow
def test_a_damaged_compiled_kernel_is_rebuilt_not_loaded(tmp_path, monkeypatch):
    """On 6b09ff3 an altered library gave other numbers, sealed as valid, and 200 flipped bits made
    every later run end in a segfault (exit 139) with no message."""
    import random

    from learners import kernels

    if kernels._compiler() is None:
        pytest.skip("no C++ compiler here")
    monkeypatch.setenv("RACING_KERNEL_CACHE", str(tmp_path / "cache"))
    path, digest = kernels._build()
    good = path.read_bytes()
    data = bytearray(good)
    rng = random.Random(64)
    for _ in range(200):
        data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
    path.write_bytes(bytes(data))
    with pytest.warns(RuntimeWarning, match="differs from the library that was built .* rebuilt, not loaded"):
        again, again_digest = kernels._build()
    assert again == path and again_digest == digest and path.read_bytes() == good
    path.with_name(path.name + ".sha256").unlink()  # a library without its record: rebuilt too
    with pytest.warns(RuntimeWarning, match="no record of its SHA-256"):
        kernels._build()
    # a whole run on a damaged cache: rebuilt, and the run completes (a fresh process loads it)
    path.write_bytes(bytes(data))
    result = run("train.py", *TINY, f"hydra.run.dir={tmp_path / 'run'}",
                 env={**ENV, "RACING_KERNEL_CACHE": str(tmp_path / "cache")})
    assert result.returncode == 0, result.stderr[-2000:]
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["numerics"]["mode"] == "fma"


def test_a_summary_with_a_final_performance_that_is_not_a_number_is_damaged(tmp_path, finished):
    folder = tmp_path / "run"
    shutil.copytree(finished, folder)
    summary = json.loads((folder / "summary.json").read_text())
    summary["final_mean"] = float("nan")
    (folder / "summary.json").write_text(json.dumps(seal(summary)))
    found = rundir.state(folder)
    assert found.kind == "damaged" and "final_mean nan, not a finite number" in found.problem


def test_report_refuses_a_metrics_file_grown_to_gigabytes_unread(tmp_path, finished):
    """On 6b09ff3 report.py read a 3 GB sparse metrics.csv whole (6.3 GB at its peak)."""
    import tracemalloc

    from analysis.report import read_run
    from engine.outputs import ROWS_LIMIT

    folder = tmp_path / "run"
    shutil.copytree(finished, folder)
    with open(folder / "metrics.csv", "r+b") as f:
        f.truncate(ROWS_LIMIT + 2**20)  # sparse
    tracemalloc.start()
    found = read_run(folder)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert found.status == "damaged" and found.rewards == [] and peak < 50 * 2**20


# ------------------------------------------------------------------ unbounded and unclear

def test_a_path_too_long_and_a_bad_kernel_variable_end_in_one_line_before_anything_is_written(tmp_path):
    long = run("train.py", *TINY, f"hydra.run.dir={tmp_path / ('x' * 300) / 'run'}")
    assert long.returncode == 2 and "File name too long" in one_line(long)
    folder = tmp_path / "run"
    isa = subprocess.run([sys.executable, ROOT / "train.py", *TINY, f"hydra.run.dir={folder}"], cwd=ROOT,
                         env={**ENV, "RACING_KERNEL_ISA": "garbage"}, capture_output=True, text=True, timeout=300)
    assert isa.returncode == 2 and "RACING_KERNEL_ISA must be one of" in one_line(isa)
    assert not folder.exists() or list(folder.iterdir()) == []
    # a sweep: refused by its whole-sweep check, before any folder (on 258b7c4 each job refused it after Hydra
    # had made the job's folder, and the sweep ended in a joblib traceback)
    sweep = tmp_path / "sweep"
    swept = subprocess.run([sys.executable, ROOT / "train.py", "-m", *TINY, "seed=1,2", f"hydra.sweep.dir={sweep}"],
                           cwd=ROOT, env={**ENV, "RACING_KERNEL_ISA": "garbage"}, capture_output=True, text=True,
                           timeout=300)
    assert swept.returncode == 2 and "The sweep was not started: " in swept.stderr, swept.stderr[-2000:]
    assert "RACING_KERNEL_ISA must be one of" in swept.stderr and "Traceback" not in swept.stderr
    assert not sweep.exists()


@pytest.mark.slow
def test_a_shared_kernel_cache_is_refused_and_left_as_it_is(tmp_path):
    """On 258b7c4 RACING_KERNEL_CACHE pointed at an existing shared folder (mode 2775 or 1777) changed its mode
    (to 2755, 1755): as root with /tmp that would break the system. Now the run says so in one line, computes
    with the portable products, and the folder keeps its mode."""
    shared = tmp_path / "shared"
    shared.mkdir()
    os.chmod(shared, 0o2775)
    env = {**ENV, "RACING_KERNEL_CACHE": str(shared), "PYTHONWARNINGS": "default"}
    result = subprocess.run([sys.executable, "train.py", *TINY, f"hydra.run.dir={tmp_path / 'run'}"], cwd=ROOT,
                            env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    (line,) = [line for line in result.stderr.splitlines() if "running numerics=portable instead" in line]
    assert "may be written by other users (mode 2775)" in line, line
    assert stat.S_IMODE(os.lstat(shared).st_mode) == 0o2775 and not any(shared.iterdir())


def test_compiled_code_is_cached_in_a_folder_of_this_users_own(tmp_path, monkeypatch):
    """TorchInductor loads the code it cached; its default folder sits in a shared /tmp, where another
    user could have made it first and planted code (found by a hostile trial)."""
    from learners import compiling

    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
    monkeypatch.setenv("RACING_KERNEL_CACHE", str(tmp_path / "cache" / "kernels"))
    (tmp_path / "cache").mkdir()
    os.mkdir(tmp_path / "cache" / "inductor", 0o777)
    os.chmod(tmp_path / "cache" / "inductor", 0o1777)  # a shared folder, as /tmp: refused, never changed
    with pytest.raises(RuntimeError, match="may be written by other users .mode 1777"):
        compiling.inductor_cache()
    assert stat.S_IMODE(os.lstat(tmp_path / "cache" / "inductor").st_mode) == 0o1777
    shutil.rmtree(tmp_path / "cache" / "inductor")
    assert compiling.inductor_cache() == str(tmp_path / "cache" / "inductor")  # made afresh: this user's alone
    assert stat.S_IMODE(os.lstat(tmp_path / "cache" / "inductor").st_mode) & 0o077 == 0
    shutil.rmtree(tmp_path / "cache" / "inductor")
    (tmp_path / "cache" / "inductor").symlink_to(tmp_path)
    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
    with pytest.raises(RuntimeError, match="cannot be used: .*symbolic link"):
        compiling.inductor_cache()
    (tmp_path / "cache" / "inductor").unlink()
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", default_cache_dir())  # as importing torch._inductor.config sets it
    assert compiling.inductor_cache() == str(tmp_path / "cache" / "inductor")  # torch's default is no choice
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "mine"))
    assert compiling.inductor_cache() == str(tmp_path / "mine")  # the user's own choice stands


@pytest.mark.parametrize("override", ["hydra.output_subdir=.hydra", "hydra/job_logging=default"])
def test_hydra_never_writes_a_file_itself(tmp_path, override):
    """Hydra writes its own record and logs by name, through links: a command that turns them on is
    refused before Hydra writes anything (found by a hostile trial: the record went through a link)."""
    victim = tmp_path / "victim"
    victim.write_text("mine\n")
    folder = tmp_path / "run"
    (folder / ".hydra").mkdir(parents=True)
    (folder / ".hydra" / "config.yaml").symlink_to(victim)
    result = run("train.py", *TINY, override, f"hydra.run.dir={folder}")
    assert result.returncode == 2 and one_line(result).startswith("Invalid configuration: hydra.")
    assert victim.read_text() == "mine\n" and sorted(p.name for p in folder.iterdir()) == [".hydra"]


def test_an_sb3_model_whose_sizes_would_exhaust_the_machine_is_refused_before_it_is_built(tmp_path):
    """net_arch [2**40] ended in an allocator traceback; [15000, 15000] took 4.6 GB and ignored SIGTERM
    for minutes (found by a hostile trial)."""
    pytest.importorskip("stable_baselines3")
    import zipfile

    from external.sb3 import ModelRefused, load_model

    path = sb3_zip(tmp_path, None, tmp_path / "marker")
    with zipfile.ZipFile(path) as archive:
        entries = {name: archive.read(name) for name in archive.namelist()}
    for net_arch, words in (([2**40], "outside 1..4096"), ([-3], "outside 1..4096"), ([15000, 15000], "outside"),
                            ([64] * 40, "at most 16"), ({"pi": [64], "evil": [1]}, "other than pi, vf and qf"),
                            ((20_000, None), "not a count of 1 to 64"),  # 20,000 critics took 7-11 GB (35048d1)
                            ((64, [4096] * 4), "more than its policy.pth holds")):  # caps kept, the product not
        data = json.loads(entries["data"])
        data["policy_kwargs"] = {"n_critics": net_arch[0], "net_arch": net_arch[1]} if isinstance(net_arch, tuple) \
            else {"net_arch": net_arch}
        with zipfile.ZipFile(tmp_path / "bad.zip", "w") as archive:
            for name, content in {**entries, "data": json.dumps(data).encode()}.items():
                archive.writestr(name, content)
        with pytest.raises(ModelRefused, match=words):
            load_model(tmp_path / "bad.zip")


@pytest.mark.parametrize("content", ["[" * 200_000 + "]" * 200_000, '{"episodes": 1' + "0" * 5000 + "}"])
def test_a_summary_nested_too_deep_or_with_a_number_too_long_is_damage_not_a_traceback(tmp_path, finished, content):
    folder = tmp_path / "run"
    shutil.copytree(finished, folder)
    (folder / "summary.json").write_text(content)
    found = rundir.state(folder)
    assert found.kind == "damaged" and "is not JSON" in found.problem


@pytest.mark.parametrize("change", [{"algo": {"a": 1}}, {"er": 5}, {"code": [1]}, {"final_mean": None},
                                    {"seed": True}])
def test_a_resealed_summary_with_fields_of_other_types_is_damage(tmp_path, finished, change):
    """report.py crashed on such fields (sorting a dict, reading a list's keys) after writing half its
    files, or counted a completed run without a final performance (found by a hostile trial)."""
    folder = tmp_path / "run"
    shutil.copytree(finished, folder)
    summary = json.loads((folder / "summary.json").read_text())
    (folder / "summary.json").write_text(json.dumps(seal({**summary, **change})))
    assert rundir.state(folder).kind == "damaged"


def test_a_sweeps_own_file_that_is_a_folder_is_refused_before_anything_is_written(tmp_path):
    (tmp_path / "sweep" / ".stop").mkdir(parents=True)
    result = run("train.py", "-m", *TINY, "hydra/launcher=basic", f"hydra.sweep.dir={tmp_path / 'sweep'}")
    assert result.returncode == 2 and ".stop is a folder" in result.stderr and "Traceback" not in result.stderr
    assert sorted(p.name for p in (tmp_path / "sweep").iterdir()) == [".stop"]


def test_demo_writes_its_pictures_through_the_door(tmp_path):
    """demo.py saved pygame's pictures by name: through a link, and blocking on a FIFO (found by a
    hostile trial)."""
    pytest.importorskip("pygame")
    victim = tmp_path / "victim"
    victim.write_text("mine\n")
    out = tmp_path / "demo"
    out.mkdir()
    (out / "trajectory.png").symlink_to(victim)
    os.mkfifo(out / "car.png")
    result = run("demo.py", "--out", str(out), timeout=120)
    assert result.returncode == 2 and "car.png" in one_line(result) and "FIFO" in one_line(result)
    assert victim.read_text() == "mine\n"


def test_a_folder_name_that_is_not_utf8_is_reported_escaped(tmp_path, finished):
    sweep = tmp_path / "sweep"
    shutil.copytree(finished.parent.parent.parent, sweep)
    os.rename(sweep / "spg" / "recent" / "seed2067791", os.fsencode(sweep / "spg" / "recent") + b"/seed\xff")
    result = run("report.py", str(sweep), "--no-figures", timeout=120)
    assert result.returncode == 0 and "Traceback" not in result.stderr, result.stderr[-2000:]
    assert "seed\\udcff" in (sweep / "report" / "runs.csv").read_text()


# ------------------------------------------------------------------ the second hostile trial's findings

@pytest.mark.slow
def test_a_cached_kernel_library_without_the_kernels_falls_back_in_one_line(tmp_path):
    """A library whose record matches but that is not the kernels (a planted one) ended in an
    AttributeError traceback; one of another user's is rebuilt, never loaded."""
    import subprocess
    import sys

    from learners import kernels

    if kernels._compiler() is None:
        pytest.skip("no C++ compiler here")
    cache = tmp_path / "cache"
    probe = ("from learners import kernels; path, digest = kernels._build(); print(path)")
    built = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, env={**ENV, "RACING_KERNEL_CACHE": str(cache)},
                           capture_output=True, text=True, timeout=300)
    path = Path(built.stdout.strip().splitlines()[-1])
    source = tmp_path / "other.c"
    source.write_text("int unrelated(void) { return 1; }\n")
    subprocess.run(["gcc", "-shared", "-fPIC", str(source), "-o", str(path)], check=True)
    import hashlib

    path.with_name(path.name + ".sha256").write_text(hashlib.sha256(path.read_bytes()).hexdigest() + "\n")
    reason = subprocess.run([sys.executable, "-c", "from learners import kernels; print(kernels.unavailable_reason())"],
                            cwd=ROOT, env={**ENV, "RACING_KERNEL_CACHE": str(cache)}, capture_output=True, text=True,
                            timeout=300)
    assert reason.returncode == 0 and "the cached library lacks" in reason.stdout, reason.stderr[-2000:]
    if os.geteuid() == 0:  # another user's library: rebuilt (root can give it away)
        os.chown(path, 65534, 65534)
        rebuilt = subprocess.run([sys.executable, "-c", "from learners import kernels; print(kernels.unavailable_reason())"],
                                 cwd=ROOT, env={**ENV, "RACING_KERNEL_CACHE": str(cache), "PYTHONWARNINGS": "default"},
                                 capture_output=True, text=True, timeout=300)
        assert rebuilt.stdout.strip() == "None" and "belongs to another user" in rebuilt.stderr
        assert os.lstat(path).st_uid == os.getuid()


def test_checkpoints_that_overlap_or_whose_name_lies_are_refused(tmp_path):
    """Two processes trained one member into one folder, and a finished member's results were
    destroyed, from a copied or renamed split-population checkpoint (found by a hostile trial)."""
    from engine.config import ConfigError
    from tests.fault_injection import stopped_after

    population = [*CHECKPOINTED, "seeds=[1,2]"]
    folder = tmp_path / "population"
    with stopped_after(2):
        train(population, folder)
    shutil.copy(folder / "checkpoint.pt", folder / "checkpoint-1.pt")
    with pytest.raises(ConfigError, match="that another checkpoint .* holds too"):
        train(population, folder)
    (folder / "checkpoint-1.pt").rename(folder / "checkpoint-7.pt")
    (folder / "checkpoint.pt").unlink()
    with pytest.raises(ConfigError, match=r"holds the members \[1, 2\], not a part starting at seed 7"):
        train(population, folder)


def test_the_slurm_launcher_stops_waiting_when_squeue_cannot_answer(monkeypatch):
    """Without squeue (or with it failing) the launcher waited forever and ignored SIGINT and SIGTERM."""
    from types import SimpleNamespace

    from hydra_plugins.racing_launcher import slurm

    job = SimpleNamespace(job_id="4242_0", paths=SimpleNamespace(result_pickle=Path("/nonexistent/result.pkl")))
    monkeypatch.setattr(slurm, "squeue_states", lambda ids: None)
    with pytest.raises(slurm.SweepJobsFailed):
        slurm.wait_for([job], poll_s=0.01, grace_s=0.01, patience_s=0.05)


@pytest.mark.slow
def test_drive_without_a_display_ends_with_its_line(tmp_path):
    """With SDL's offscreen driver (no display, SDL_VIDEODRIVER unset) drive.py waited for a window
    no one could close (found by a hostile trial)."""
    pytest.importorskip("pygame")
    result = run("drive.py", "--max-steps", "5", "--no-oracle", env={**ENV, "SDL_VIDEODRIVER": "offscreen"},
                 timeout=120)
    assert result.returncode == 0 and result.stdout.strip().splitlines()[-1].startswith("you: ")


def test_analysis_and_track_outputs_are_checked_before_the_work(tmp_path):
    runs_csv = tmp_path / "runs.csv"
    runs_csv.write_text("er,algo,seed,status,final_mean\nmemory,sac,1,completed,1.0\n")
    os.mkfifo(tmp_path / "fifo.md")
    compare = run("analysis/compare.py", str(runs_csv), str(runs_csv), "--markdown", str(tmp_path / "fifo.md"))
    assert compare.returncode == 2 and "FIFO" in compare.stderr and "Traceback" not in compare.stderr
    track = tmp_path / "oval.png"
    shutil.copy(ROOT / "racing" / "tracks" / "oval.csv", track)
    show = run("tracks.py", "show", str(track))
    assert show.returncode == 2 and "is the track file itself" in show.stderr
    assert track.read_bytes() == (ROOT / "racing" / "tracks" / "oval.csv").read_bytes()
    runs_csv.write_text("er,algo,seed,status,final_mean\nmemory,sac,1,completed,nan\n")
    nan = run("analysis/compare.py", str(runs_csv), str(runs_csv))
    assert nan.returncode == 2 and "not a finite number" in nan.stderr


@pytest.mark.parametrize("path, value, words", [
    (("network", "actor_hidden"), [65536] * 64, "networks of"),  # each layer within its ceiling, 1.1 TB in all
    (("network", "actor_hidden"), [2048, 2048], "ask for an actor of at least 4,214,786 parameters"),
    (("network", "actor_hidden"), [10**9], "above its ceiling"),
    (("algo", "spg", "num_samples"), 10**9, "above its ceiling"),
    (("env", "options", "max_steps"), 10**9, "max_steps must be an integer in"),
    (("env", "past_steps"), -3, "past_steps"),
    (("algo", "loss"), "tdmpc2", "records settings no run could have"),  # another learner's record over SPG weights
])
def test_a_run_whose_record_asks_for_more_than_it_holds_is_refused_before_anything_is_built(
        tmp_path, finished, path, value, words):
    """A downloaded run folder whose summary (resealed: the seal guards damage, not forgery) asks for sizes
    its weights do not hold, or no run could have: evaluate.py and score.py refuse it in one line before
    any network is built (the first built 1.1 TB of layers on 258b7c4)."""
    folder = tmp_path / "run"
    shutil.copytree(finished, folder)
    summary = json.loads((folder / "summary.json").read_text())
    node = summary["settings"]
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    (folder / "summary.json").write_text(json.dumps(seal(summary)))
    for script, args in (("evaluate.py", [str(folder)]), ("score.py", [str(folder), "--tracks", "1"])):
        line = one_line(run(script, *args, timeout=120))
        assert words in line and "summary.json" in line, (script, line)


@pytest.mark.slow
def test_a_planner_whose_record_asks_for_samples_beyond_the_machine_is_refused_before_it_plans(tmp_path):
    """A TD-MPC2-style run resealed with samples=100,000, iterations=1,000, horizon=150 (each within its ceiling)
    passed the weights' check and then asked the allocator for 120 GB, a traceback (found by a hostile trial; here
    the horizon is the episode's 40 steps)."""
    folder = tmp_path / "run"
    train(["algo=tdmpc2", "er=memory", "episodes=1", "env.options.max_steps=40", "progress=false", "logger=none"],
          folder)
    summary = json.loads((folder / "summary.json").read_text())
    summary["settings"]["algo"]["tdmpc2"].update(samples=100_000, iterations=1_000, horizon=40)
    (folder / "summary.json").write_text(json.dumps(seal(summary)))
    line = one_line(run("evaluate.py", str(folder), timeout=120))
    assert "to act with, more than this machine has available" in line, line
