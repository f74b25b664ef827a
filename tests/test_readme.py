"""Every command the README and the docs/ pages show runs, at a tiny size (two episodes, a
temporary folder).

Commands are read from the pages themselves, so a documented command that breaks fails here.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from tests.test_config import CELLS
from tests.test_train import ROOT, read_rows, run_train

PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]  # not docs/results/: records of runs
README = "\n".join(page.read_text() for page in PAGES)
# Commands run by other tests at a tiny size (or that need a cluster), and where.
ELSEWHERE = {
    "clean_sweep.py": "tests/test_launchers.py::test_clean_sweep_runs_an_export_of_the_commit",
    "hydra/launcher=slurm": "tests/test_slurm.py (a real single-node SLURM) and tests/test_launchers.py",
    "--oracle": "tests/test_oracle.py::test_the_documented_oracle_command_runs",
    "compile=true": "tests/test_compile.py (compiled SPG-p, SAC and TD3 runs at a tiny size)",
    "processes=2": "tests/test_population.py::test_a_population_split_over_processes_killed_and_resumed_gives_its_"
                   "unsplit_results",
}


def readme_commands(script: str, include_elsewhere: bool = False) -> list[list[str]]:
    """Each distinct ``python <script> ...`` line of the README and docs/ (continuations joined,
    comments cut); without ``include_elsewhere``, not those another test runs (``ELSEWHERE``)."""
    text = README.replace("\\\n", " ")
    found = []
    for match in re.finditer(rf"^\s*(?:\.venv/bin/)?python3? {re.escape(script)}(.*)$", text, re.MULTILINE):
        line = match.group(1).split("#")[0]
        if not include_elsewhere and any(key in line for key in ELSEWHERE):
            continue
        args = shlex.split(line)
        if args not in found:
            found.append(args)
    return found


DOWNLOADED = "racetrack-database/tracks/"  # where the docs' commands read a downloaded TUM circuit


def stand_in_circuits(args: list[str], folder: Path) -> list[str]:
    """``args`` with every downloaded TUM circuit the docs name (``DOWNLOADED``) replaced by a
    circuit the project makes in the same layout (the database's files are not shipped)."""
    from racing.track_file import make_circuit, write_rows

    out = []
    for arg in args:
        if DOWNLOADED in arg:
            start = arg.index(DOWNLOADED)
            name = arg[start:].split()[0]
            folder.mkdir(parents=True, exist_ok=True)
            made = write_rows(folder / Path(name).name, make_circuit(300))
            arg = arg.replace(name, str(made))
        out.append(arg)
    return out


def stand_in_start(args: list[str], folder: Path) -> list[str]:
    """``args`` with the run ``algo.td.start_from`` names replaced by a two-episode SAC run of the command's seed
    in ``folder`` (the docs name a run a reader has trained)."""
    if not any(a.startswith("algo.td.start_from=") for a in args):
        return args
    seed = next((a for a in args if a.startswith("seed=")), "seed=2067791")
    result = run_train("algo=sac", "er=prioritised", seed, "episodes=2", "progress=false", f"hydra.run.dir={folder}")
    assert result.returncode == 0, result.stderr[-3000:]
    return [f"algo.td.start_from={folder}" if a.startswith("algo.td.start_from=") else a for a in args]


def tiny(args: list[str], out: Path) -> list[str]:
    """The same command at two episodes, writing into ``out``."""
    args = stand_in_circuits(args, out / "circuits")
    args = stand_in_start(args, out.parent / f"{out.name}-start")
    keep = [a for a in args if not a.startswith("episodes=")]
    extra = ["episodes=2", "progress=false"]
    if "-m" in args:
        extra.append(f"hydra.sweep.dir={out}")
        if any(a.startswith("+experiment=") for a in args):
            extra.append("seeds=[2067791]")  # one track per cell instead of five
    else:
        extra.append(f"hydra.run.dir={out}")
    return keep + extra


TRAIN = readme_commands("train.py")


def test_the_readme_shows_what_these_tests_run():
    assert [] in TRAIN  # the main job: python train.py
    assert any("+experiment=paper_grid" in c for c in TRAIN)
    assert readme_commands("report.py") and readme_commands("evaluate.py")
    assert "clean_sweep.py +experiment=full_grid" in README and "hydra/launcher=slurm" in README


@pytest.mark.slow
@pytest.mark.parametrize("args", TRAIN, ids=[" ".join(c) or "defaults" for c in TRAIN])
def test_readme_train_command(tmp_path, args):
    result = run_train(*tiny(args, tmp_path))
    if "logger=tensorboard" in args and "needs the tensorboard package" in result.stderr:
        assert result.returncode == 2 and "Traceback" not in result.stderr  # the extra is not installed
        return
    assert result.returncode == 0, result.stderr[-3000:]
    summaries = list(tmp_path.rglob("summary.json"))
    assert summaries
    for path in summaries:
        summary = json.loads(path.read_text())
        assert summary["status"] == "completed" and summary["episodes"] == 2
        assert summary["code"]["source"]
    if "+experiment=paper_grid" in args:  # every cell of Table 1, on one track here
        assert len(summaries) == len(CELLS) == 15
        for path in summaries:
            summary = json.loads(path.read_text())
            assert f"{summary['er']}-{summary['algo']}" in CELLS and summary["settings"]["seed"] == 2067791
            rows = read_rows(path.parent / "metrics.csv")
            assert [int(r["episode"]) for r in rows] == [0, 1]
            assert rows[1]["critic/loss_critic"] != "" and rows[1]["actor/loss_objective"] != ""
            assert (path.parent.parent / ".hydra" / "config.yaml").exists()  # the cell's job folder


@pytest.mark.slow
def test_readme_report_and_evaluate_commands(tmp_path, capsys):
    """The README's report and evaluate lines, on a two-run sweep in place of the paper grid."""
    pytest.importorskip("matplotlib", reason="the report's figures and the video need the render extra")
    import evaluate
    import report

    sweep = tmp_path / "paper_grid"
    result = run_train("-m", "+cell=memory-spg_p_multi,recent-ppo", "seed=2067791", "episodes=2",  # one process
                       "progress=false", "logger=none", "hydra/launcher=basic", f"hydra.sweep.dir={sweep}")
    assert result.returncode == 0, result.stderr[-3000:]
    for args in readme_commands("report.py"):
        if "paper_grid" in args[0]:
            assert report.main([str(sweep), *args[1:]]) == 0
    for args in readme_commands("evaluate.py"):
        args = [str(sweep / Path(args[0]).relative_to("outputs/sweeps/paper_grid")), *args[1:]]
        args = [str(tmp_path / Path(a).name) if a.endswith((".gif", ".mp4", ".csv")) else a for a in args]
        args[args.index("--episodes") + 1] = "1"
        assert evaluate.main(args) == 0
    assert (sweep / "report" / "table.md").exists() and list(tmp_path.glob("*.gif"))
    # the film is of the run's own track, and its line says so (on 258b7c4: the first of --tracks, unnamed)
    assert "track 2067791 (its own): " in capsys.readouterr().out


def test_every_relative_link_in_the_docs_points_at_a_file():
    """A page that moves (a results folder superseded, a doc renamed) leaves no dead link behind:
    every relative Markdown link in README.md and docs/ (results pages included) resolves."""
    dead = []
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        prose = re.sub(r"```.*?```|`[^`\n]*`", "", page.read_text(), flags=re.DOTALL)  # not code
        for target in re.findall(r"\]\(([^)\s]+)\)", prose):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue  # a URL or an anchor on the same page
            if not (page.parent / target.split("#")[0]).exists():
                dead.append(f"{page.relative_to(ROOT)}: {target}")
    assert not dead, "dead links:\n" + "\n".join(dead)


def _sweep_values(override: str) -> list[str]:
    """``key=a,b`` as ``[key=a, key=b]`` (commas inside brackets or quotes are one value's)."""
    key, _, value = override.partition("=")
    if value.startswith(("[", "'", '"', "glob(", "range(")) or "," not in value:
        return [override]
    return [f"{key}={v}" for v in value.split(",")]


@pytest.mark.slow
def test_every_documented_sweep_of_the_current_code_composes():
    """Each ``clean_sweep.py`` line of the README and docs/ that runs the current code (no
    ``--commit`` of an older one) composes, every swept value: a key misspelt in a documented
    sweep fails here, not an hour into it. (Running one: tests/test_launchers.py.)"""
    from engine.config import RunConfig

    checked = 0
    for args in readme_commands("clean_sweep.py", include_elsewhere=True):
        if "--commit" in args:
            continue
        overrides = [_sweep_values(a) for a in args if "=" in a and not a.startswith("hydra.")]
        first = [values[0] for values in overrides]
        for i, values in enumerate(overrides):  # each swept value, the other keys at their first
            for value in values:
                RunConfig.compose(*first[:i], value, *first[i + 1:])
                checked += 1
    assert checked >= 2  # the README's paper and full grids at least (the journal's sweeps are history: not checked)


@pytest.mark.slow
def test_the_quick_tier_selects_every_test_file_but_the_marked_slow_tests():
    """The README's quick tier (``-m "not slow"``): it deselects exactly the tests marked ``slow`` (at the
    test, or a parameter of it) and keeps a test of every test file that has a fast one."""
    assert '.venv/bin/python -m pytest -m "not slow"' in README
    result = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-m", "not slow", "-p",
                             "no:cacheprovider", "-o", "addopts="], cwd=ROOT, capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stdout[-2000:]
    selected = {line for line in result.stdout.splitlines() if "::" in line}
    slow = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-m", "slow", "-p",
                           "no:cacheprovider", "-o", "addopts="], cwd=ROOT, capture_output=True, text=True, timeout=300)
    marked = {line for line in slow.stdout.splitlines() if "::" in line}
    assert not selected & marked and len(marked) > 100 and len(selected) > 400
    assert len({test.split("::")[0] for test in selected}) >= 30


# Each tool whose command a page shows, and the test that runs that page's lines of it at a tiny size.
DOCUMENTED_TOOLS = {
    "train.py": "tests/test_readme.py", "report.py": "tests/test_readme.py", "evaluate.py": "tests/test_readme.py",
    "clean_sweep.py": "tests/test_readme.py", "tracks.py": "tests/test_track_files.py",
    "score.py": "tests/test_benchmark.py", "drive.py": "tests/test_benchmark.py", "baseline.py": "tests/test_baseline.py",
    "imitate.py": "tests/test_imitation.py", "-m analysis.driving": "tests/test_driving.py",
    "-m analysis.pessimism": "tests/test_pessimism.py", "-m pupil.search": "tests/test_search.py",
    "-m analysis.caution": "tests/test_caution.py", "-m analysis.planner": "tests/test_planner.py",
    "-m benchmark.leaderboard": "tests/test_benchmark.py", "-m tests.fault_injection": "tests/test_fault_injection.py",
    "-m tests.slurm_cluster": "tests/test_slurm.py", "-m pytest": "tests/test_readme.py",
}


def test_every_documented_command_is_run_by_a_test():
    """Every ``python <tool>`` line a page shows (README.md, docs/*.md) names a tool whose test reads the pages'
    lines of it (``readme_commands``) or the command itself and runs it small: a new documented tool, or a
    tool whose test stops reading the docs, fails here."""
    text = README.replace("\\\n", " ")
    shown = set(re.findall(r"^\s*(?:\.venv/bin/)?python3? (-m [\w.]+|[\w]+\.py)", text, re.MULTILINE)) - {"-m venv"}
    unlisted = sorted(shown - set(DOCUMENTED_TOOLS))
    assert not unlisted, f"documented commands no test runs: {unlisted} (add a test and its line in DOCUMENTED_TOOLS)"
    for tool in shown:
        source = (ROOT / DOCUMENTED_TOOLS[tool]).read_text()
        named = tool.removeprefix("-m ").split(".")[-1]  # the script, or the module as its test imports it
        assert f'readme_commands("{tool}"' in source or named in source, (tool, DOCUMENTED_TOOLS[tool])


def test_every_committed_figure_is_shown_on_a_page():
    """A figure a run made and the project committed is shown (``![...](...)``) on a page of README.md or
    docs/ (the page that discusses it), not left in a folder for nobody to find."""
    figures = {p.resolve() for p in (ROOT / "docs").rglob("*") if p.suffix in (".png", ".gif", ".svg", ".jpg")}
    shown = set()
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        for target in re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", page.read_text()):
            shown.add((page.parent / target).resolve())
    missing = sorted(str(p.relative_to(ROOT)) for p in figures - shown)
    assert not missing, "figures shown on no page:\n" + "\n".join(missing)
