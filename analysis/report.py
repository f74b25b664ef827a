"""Reading a sweep folder and laying its results out as the paper's Table 1.

A run is a folder with ``metrics.csv`` and (once finished) ``summary.json``, judged by the one rule
of ``engine.rundir``: runs without a summary are *partial* (killed or still running), runs whose
summary is not one or whose files differ from what it records are *damaged*; both are listed with
the reason, never counted.
"""

from __future__ import annotations

import csv
import io
import math
import statistics
from engine.names import markdown_cell
from dataclasses import dataclass, field
from pathlib import Path

from engine.config import algo_learners, algo_titles
from engine.outputs import METRICS_FILE, ROWS_LIMIT, SUMMARY_FILE, RunFolderError
from door import files

PAPER_TABLE = Path(__file__).resolve().parent / "data" / "paper_table1.csv"
EPISODE_STEPS = 200  # racing.RacingConfig.max_steps (not imported: the report reads folders only)
PAPER_EPISODES = 201  # the budget of the paper's Table 1 (episodes 0..200): its values compare with runs of it only
ORACLE_TABLE = Path(__file__).resolve().parent / "data" / "oracle.csv"  # evaluate.py --oracle --table
TUNING_ORACLE_TABLE = ORACLE_TABLE.with_name("oracle_tuning.csv")  # the same for the tuning tracks 1001-1003
ER_ROWS = ("recent", "memory", "hybrid")
ALGO_COLUMNS = ("ppo", "ppo_log", "spg", "spg_multi", "spg_p", "spg_p_multi")
COLUMN_TITLES = {"ppo": "PPO linear", "ppo_log": "PPO log", "spg": "SPG single", "spg_multi": "SPG multiple",
                 "spg_p": "SPG-p single", "spg_p_multi": "SPG-p multiple"}
# every algorithm a run folder can name, for tables that list cells beyond the paper's: conf/algo's titles
# (the paper's with Table 1's column titles), a cell's own name and the baselines'
ALGO_TITLES = {**algo_titles(), **COLUMN_TITLES, "sac_sb3": "SAC at SB3's settings",
               "sb3_sac": "Stable-Baselines3 SAC", "sb3_ppo": "Stable-Baselines3 PPO"}


@dataclass
class Run:
    path: Path
    status: str  # completed, diverged, partial (killed or running), damaged (engine.rundir)
    algo: str | None = None
    er: str | None = None
    seed: int | None = None
    final_mean: float | None = None
    rewards: list[float] = field(default_factory=list)
    code: dict | None = None  # summary.json's "code" (engine.version.code_version())
    track_mode: str = "fixed"  # env.track: fixed (the seed's track) or random (a new track per episode)
    evaluation: dict | None = None  # summary.json's "evaluation" (eval_seeds set), or None
    wall_time: float | None = None  # seconds per run: the population's wall time (all sessions) over its size
    numerics: str = "not recorded"  # the numerics mode and the kernels that ran (numerics_label)
    episode_steps: int = EPISODE_STEPS  # environment steps per episode (env.options.max_steps; racing's default 200)
    cpu_time: float | None = None  # seconds per run: the CPU time of the process that trained it over its size
    problem: str | None = None  # a damaged run's: which file, and what is wrong with it
    sealed: bool = True  # its summary carries its own digest (False: written before summaries were sealed)
    budget: int | None = None  # the episodes it was planned for (summary.json's episodes_planned): its training budget

    @property
    def version(self) -> str:
        """The code's identity: its source hash (and the one it resumed from, if different)."""
        if not self.code or not self.code.get("source"):
            return "not recorded"
        earlier = self.code.get("resumed_from")
        return self.code["source"] + (f" resumed from {earlier.get('source')}" if earlier else "")


@dataclass
class Cell:
    er: str
    algo: str
    finals: list[float]
    diverged: int
    paper_mean: float | None
    paper_sem: float | None
    budgets: tuple[int, ...] = ()  # the episode budgets of its completed runs (one, unless mixed)

    @property
    def n(self) -> int:
        return len(self.finals)

    @property
    def comparable(self) -> bool:
        """Whether its runs are of the paper's budget (all of them), so that the paper's value compares."""
        return self.budgets == (PAPER_EPISODES,)

    @property
    def mean(self) -> float | None:
        return math.fsum(self.finals) / self.n if self.n else None

    @property
    def sem(self) -> float | None:
        if self.n < 2:
            return None
        m = self.mean
        return math.sqrt(math.fsum((x - m) ** 2 for x in self.finals) / (self.n - 1) / self.n)

    @property
    def z(self) -> float | None:
        """(ours - paper) in units of the combined standard error; None unless the runs are of the
        paper's budget (``comparable``)."""
        if self.mean is None or self.sem is None or self.paper_mean is None or not self.comparable:
            return None
        combined = math.hypot(self.sem, self.paper_sem or 0.0)
        return (self.mean - self.paper_mean) / combined if combined > 0 else None


def numerics_label(summary: dict) -> str:
    """``"portable (AVX2 kernels)"``: the run's numerics mode (``engine.numerics``) and the torch
    kernels that ran, with ``", compiled"`` if its update steps were compiled (``compile=true``:
    other rounding). Runs from before the modes existed ran the machine's own kernels: native."""
    effect = summary.get("numerics") or {"mode": "native", "kernels": (summary.get("software") or {}).get("cpu")}
    compiled = ", compiled" if (summary.get("compile") or {}).get("enabled") else ""
    return f"{effect.get('mode')} ({effect.get('kernels') or 'unknown'} kernels){compiled}"


def numerics_groups(runs: list[Run]) -> dict[str, list[Run]]:
    """Finished runs grouped by ``Run.numerics``: runs of two groups rerun bit for bit on different CPUs."""
    return _finished_by(runs, lambda run: run.numerics)


def _finished_by(runs: list[Run], key) -> dict[str, list[Run]]:
    groups: dict[str, list[Run]] = {}
    for run in runs:
        if run.status in ("completed", "diverged"):
            groups.setdefault(key(run), []).append(run)
    return groups


def find_runs(sweep_dir, say: str | None = None) -> list[Run]:
    """Every run folder under ``sweep_dir`` (a folder, or a list of them; any depth), finished or not, each run
    once (``engine.runset.read_runs``: links and copies counted once; ``say``: the tool that names them)."""
    from engine.runset import read_runs

    folders = [Path(p) for p in sweep_dir] if isinstance(sweep_dir, (list, tuple)) else [Path(sweep_dir)]
    for folder in folders:
        if not folder.is_dir():
            raise FileNotFoundError(f"{folder} is not a folder; give the sweep's output folder "
                                    "(e.g. outputs/sweeps/paper_grid)")
    try:
        found = read_runs(folders, unfinished=True, skip_named="report", say=say)
    except RunFolderError:
        raise FileNotFoundError(f"no runs under {', '.join(map(str, folders))}: expected folders with {SUMMARY_FILE} "
                                f"and {METRICS_FILE}, as train.py writes them") from None
    return [read_run(folder) for folder in found.runs]


def read_run(folder: Path) -> Run:
    """The run in ``folder`` as ``engine.rundir`` judges it: finished (its summary), partial (no
    summary yet: killed or running) or damaged (with the reason); never taken for another state."""
    from engine import rundir

    found = rundir.state(folder)  # first: a finished run's metrics.csv is read only at the size its summary records
    recorded = ((found.summary or {}).get("files") or {}).get(METRICS_FILE) if found.kind == "finished" else None
    rewards = _read_rewards(folder / METRICS_FILE, recorded["bytes"] if recorded else ROWS_LIMIT)
    if found.kind in ("empty", "resumable"):
        return Run(folder, "partial", rewards=rewards)
    if found.kind == "damaged":
        return Run(folder, "damaged", rewards=rewards, problem=found.problem)
    summary = found.summary
    try:
        from engine.outputs import DIGEST_KEY

        settings = summary.get("settings") or {}
        algo_settings = settings.get("algo")  # a mapping for train.py's runs (external ones record their own)
        mislabelled = _mislabelled(summary["algo"], algo_settings.get("loss") if isinstance(algo_settings, dict) else None)
        if mislabelled:
            return Run(folder, "damaged", rewards=rewards, problem=f"{folder / SUMMARY_FILE}: {mislabelled}")
        size = (summary.get("population") or {}).get("size") or 1
        wall = summary.get("wall_time_s")
        if summary.get("resumed_at") and (wall is None or "wall_time_session_s" not in summary):
            # a resumed run whose earlier sessions' wall time was not recorded: its timed phases
            # (collection and training), which are summed over sessions and are nearly all of it
            wall = math.fsum(v for k, v in summary.items() if k.startswith("time/")) or None
        return Run(folder, summary["status"], summary["algo"], summary["er"], int(summary["seed"]),
                   summary.get("final_mean"), rewards, summary.get("code"),
                   (settings.get("env") or {}).get("track", "fixed"), summary.get("evaluation"),
                   wall / size if wall is not None else None, numerics_label(summary),
                   int(((settings.get("env") or {}).get("options") or {}).get("max_steps") or EPISODE_STEPS),
                   summary["cpu_time_s"] / size if summary.get("cpu_time_s") is not None else None,
                   sealed=DIGEST_KEY in summary, budget=rundir.training_budget(summary))
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        return Run(folder, "damaged", rewards=rewards, problem=f"{folder / SUMMARY_FILE}: a field is malformed ({err!r})")


def _mislabelled(name: str, learner: str | None) -> str | None:
    """Why a run's name is not what it trained (None: it is): a run named as one of conf/algo's algorithms
    (``algo.name``) but recorded training another learner (``settings.algo.loss``) would land in that
    algorithm's cell. A run is grouped by what it recorded, never by its folder or its name alone."""
    declared = algo_learners().get(name)
    if declared is None or learner is None or declared == learner:
        return None
    return (f"its name says {name} (conf/algo/{name}.yaml trains {declared}), but it recorded training {learner} "
            "(settings.algo.loss): give such a run a name of its own (algo.name=...)")


def code_versions(runs: list[Run]) -> dict[str, list[Run]]:
    """Finished runs grouped by the version of the code that made them (see ``Run.version``)."""
    return _finished_by(runs, lambda run: run.version)


def versions_markdown(groups: dict[str, list[Run]]) -> str:
    """One line per code version and numerics: its commit, the numerics, and how many runs it made."""
    from engine.version import describe

    lines = []
    for key, members in sorted(groups.items(), key=lambda kv: -len(kv[1])):
        for numerics, runs in sorted(numerics_groups(members).items(), key=lambda kv: -len(kv[1])):
            lines.append(f"Code: {describe(members[0].code)}; numerics: {numerics} ({len(runs)} runs)")
    return "\n".join(lines) + "\n"


def _read_rewards(path: Path, limit: int) -> list[float]:
    """The learning curve in metrics.csv (read only if it holds at most ``limit`` bytes); a last row cut
    short (a run killed while appending it) is left out, as a resume drops it; any other malformed
    row, or a file that is not a regular one of at most that size: no curve."""
    try:
        rows = list(csv.DictReader(io.StringIO(files.read_text(path, limit, "metrics.csv"), newline="")))
        if rows and None in rows[-1].values():  # fields missing: a row cut short
            rows = rows[:-1]
        return [float(row["total_reward"]) for row in rows]
    except (OSError, csv.Error, KeyError, ValueError, TypeError):  # FileRefused is a ValueError
        return []


def _read_csv(path: Path, what: str) -> list[dict]:
    """The rows of a small shipped CSV table (at most 16 MB); '#' lines are comments."""
    return files.read_csv(path, 16 << 20, what)


def _write_csv(path: Path, header: list[str], rows) -> None:
    """A CSV table written whole (``door.files.write_atomic``), no cell a spreadsheet runs as a formula
    (``engine.names.csv_cell``)."""
    from engine.names import csv_cell

    text = io.StringIO(newline="")
    writer = csv.writer(text)
    writer.writerow(header)
    writer.writerows([csv_cell(value) for value in row] for row in rows)
    files.write_text(path, text.getvalue())


def read_paper_table(path: Path = PAPER_TABLE) -> dict[tuple[str, str], tuple[float, float]]:
    """{(er, algo): (mean, sem)} in this project's names."""
    rows = _read_csv(path, "table of the paper's results")
    table = {}
    for row in rows:
        er = "hybrid" if row["er_mode"] == "both" else row["er_mode"]
        algo = row["algorithm"]
        if algo.startswith("spg") and row["epochs"] == "multiple":
            algo += "_multi"
        table[(er, algo)] = (float(row["final_mean"]), float(row["final_sem"]))
    return table


def cells(runs: list[Run], paper: dict[tuple[str, str], tuple[float, float]]) -> list[Cell]:
    """One cell per (er, algo) that has runs or a paper value, in the table's order."""
    out = []
    for er in ER_ROWS:
        for algo in ALGO_COLUMNS:
            mine = [r for r in runs if (r.er, r.algo) == (er, algo)]
            done = [r for r in mine if r.status == "completed" and r.final_mean is not None]
            diverged = sum(r.status == "diverged" for r in mine)
            paper_mean, paper_sem = paper.get((er, algo), (None, None))
            budgets = tuple(sorted({r.budget for r in done if r.budget is not None}))
            if mine or paper_mean is not None:
                out.append(Cell(er, algo, [r.final_mean for r in done], diverged, paper_mean, paper_sem, budgets))
    return out


def _fmt(cell: Cell | None) -> str:
    if cell is None:
        return ""
    parts = []
    if cell.n:
        spread = f" ± {cell.sem:.1f}" if cell.sem is not None else " ± n/a (one run)"
        budget = (f"{cell.budgets[0]} episodes" if len(cell.budgets) == 1
                  else f"mixed budgets: {', '.join(map(str, cell.budgets))} episodes" if cell.budgets
                  else "budget not recorded")
        parts.append(f"{cell.mean:.1f}{spread} (n={cell.n}; {budget})")
    if cell.diverged:
        parts.append(f"{cell.diverged} diverged")
    if cell.paper_mean is not None:
        compared = "" if not cell.n or cell.comparable else f" at {PAPER_EPISODES} episodes: not compared"
        parts.append(f"paper {cell.paper_mean:.1f} ± {cell.paper_sem:.1f}{compared}")
    if cell.z is not None:
        parts.append(f"Δ = {cell.z:+.1f} SE")
    return "<br>".join(parts) if parts else "not run"


def table_markdown(table: list[Cell]) -> str:
    by_key = {(c.er, c.algo): c for c in table}
    lines = ["| ER mode | " + " | ".join(COLUMN_TITLES[a] for a in ALGO_COLUMNS) + " |",
             "|---|" + "---|" * len(ALGO_COLUMNS)]
    for er in ER_ROWS:
        lines.append(f"| {er} | " + " | ".join(_fmt(by_key.get((er, a))) for a in ALGO_COLUMNS) + " |")
    notes = budget_notes(table)
    return "\n".join(lines) + "\n" + ("\n" + "\n".join(notes) + "\n" if notes else "")


def budget_notes(table: list[Cell]) -> list[str]:
    """What the table's budgets mean for its comparisons (empty when every run is of the paper's budget)."""
    notes = []
    other = sorted({b for c in table if c.n for b in c.budgets} - {PAPER_EPISODES})
    if other:
        notes.append(f"Runs of {', '.join(map(str, other))} episodes are not compared with the paper's values, which "
                     f"are final performances after {PAPER_EPISODES} episodes.")
    mixed = [f"{c.er} / {COLUMN_TITLES[c.algo]}" for c in table if len(c.budgets) > 1]
    if mixed:
        notes.append(f"Cells averaging runs of different budgets (their mean is of unlike runs): {', '.join(mixed)}.")
    return notes


def write_table_csv(table: list[Cell], path: Path) -> None:
    _write_csv(path, ["er", "algo", "n", "mean", "sem", "diverged", "paper_mean", "paper_sem", "z", "episodes"],
               [[c.er, c.algo, c.n, _num(c.mean), _num(c.sem), c.diverged, _num(c.paper_mean), _num(c.paper_sem),
                 _num(c.z), ";".join(map(str, c.budgets))] for c in table])


def read_oracles() -> dict[int, float]:
    """{track seed: the oracle's mean total reward} over every shipped table: the evaluation tracks'
    (``ORACLE_TABLE``) and the tuning tracks' (``TUNING_ORACLE_TABLE``)."""
    return {**read_oracle(), **read_oracle(TUNING_ORACLE_TABLE)}


def read_oracle(path: Path | None = None) -> dict[int, float]:
    """{track seed: the oracle's mean total reward} (``evaluate.py --oracle --table``; default
    ``analysis/data/oracle.csv``), {} if absent."""
    path = Path(path if path is not None else ORACLE_TABLE)
    if not path.exists():
        return {}
    return {int(row["track"]): float(row["mean_reward"]) for row in _read_csv(path, "table of oracle scores")}


def normalised(run: Run, oracle: dict[int, float]) -> float | None:
    """A run's final performance on the oracle's scale of its track: 0 = standing still (total
    reward 0), 1 = the oracle. None for runs on random tracks or tracks the oracle has not scored."""
    if run.track_mode != "fixed" or run.final_mean is None or run.seed not in oracle:
        return None
    return run.final_mean / oracle[run.seed]


def write_runs_csv(runs: list[Run], path: Path, root: Path, oracle: dict[int, float] | None = None) -> None:
    """One row per run folder: cell, track seed, final performance, status, code version, numerics,
    and, where the oracle scored the track, its score and the run's oracle-normalised score."""
    oracle = oracle or {}
    rows = []
    for r in sorted(runs, key=lambda r: (r.er or "", r.algo or "", r.seed or -1, str(r.path))):
        final = "" if r.final_mean is None else repr(float(r.final_mean))
        own, unseen = ((repr(float(r.evaluation["own_track"])), repr(float(r.evaluation["mean"])))
                       if r.evaluation else ("", ""))
        score = normalised(r, oracle)
        rows.append([r.er or "", r.algo or "", "" if r.seed is None else r.seed, r.status, final,
                     len(r.rewards), r.version, r.path.relative_to(root).as_posix(), r.track_mode, own, unseen,
                     r.numerics, repr(oracle[r.seed]) if score is not None else "",
                     repr(score) if score is not None else ""])
    _write_csv(path, ["er", "algo", "seed", "status", "final_mean", "episodes", "code", "folder", "train_tracks",
                      "eval_own_track", "eval_unseen_mean", "numerics", "oracle", "normalised"], rows)


def _num(value: float | None) -> str:
    return "" if value is None else f"{value:.4f}"


# ------------------------------------------------------------------ the paper's conclusions
PAPER_SEEDS = (2067791, 5468063, 5412436, 8273186, 773203)
COLLAPSE_BELOW = 20.0  # a final performance below this: the car stands still or keeps crashing
SPG_PAIRS = (("spg", "spg_p"), ("spg_multi", "spg_p_multi"))  # without and with prioritisation


# The fewest tracks a paired verdict is drawn from. A percentile bootstrap over n tracks draws the
# worst track n times with probability n**-n: for n <= 3 that is at least 1/27, above 2.5%, so the
# interval's lower end is the smallest per-track difference itself and "above 0" says only that
# every track was higher, which three tracks show by chance one time in eight.
MIN_VERDICT_TRACKS = 4


def paired_sign(low: float, high: float, tracks: int) -> int | None:
    """The verdict of a paired interval over ``tracks`` tracks: +1 above 0, -1 below, 0 holding 0;
    None on fewer than ``MIN_VERDICT_TRACKS`` tracks (or without an interval)."""
    if tracks < MIN_VERDICT_TRACKS or math.isnan(low):
        return None
    return 1 if low > 0 else -1 if high < 0 else 0


@dataclass
class Effect:
    """A paired effect between cells over tracks, with its 95% bootstrap interval over tracks."""

    claim: str
    label: str
    value: float
    low: float
    high: float
    tracks: int

    @property
    def verdict(self) -> str:
        return {None: "too few tracks", 1: "holds", -1: "reversed", 0: "undecided"}[
            paired_sign(self.low, self.high, self.tracks)]


def finals_by_track(runs: list[Run], er: str, algo: str, seeds: set[int] | None = None) -> dict[int, float]:
    """{track seed: final performance} of a cell's completed runs (optionally only ``seeds``)."""
    return {r.seed: r.final_mean for r in runs
            if (r.er, r.algo) == (er, algo) and r.status == "completed" and r.final_mean is not None
            and (seeds is None or r.seed in seeds)}


def paired_bootstrap(a: dict[int, float], b: dict[int, float], statistic, reps: int = 10000,
                     seed: int = 0) -> tuple[float, float, float, int]:
    """``statistic(a_values, b_values)`` over the tracks both cells have, and its 95% percentile
    interval from resampling tracks with replacement (the same tracks for both cells)."""
    import numpy as np

    tracks = sorted(set(a) & set(b))
    x = np.array([a[t] for t in tracks])
    y = np.array([b[t] for t in tracks])
    if len(tracks) < 2:  # no interval; an SD of one track is not a number either (nan, said as n/a)
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            value = float(statistic(x, y)) if tracks else float("nan")
        return value, float("nan"), float("nan"), len(tracks)
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(tracks), size=(reps, len(tracks)))
    stats = np.array([statistic(x[p], y[p]) for p in picks])
    low, high = np.percentile(stats, [2.5, 97.5])
    return float(statistic(x, y)), float(low), float(high), len(tracks)


def _mean_difference(x, y):
    return (x - y).mean()


def _sd_difference(x, y):
    return x.std(ddof=1) - y.std(ddof=1)


def conclusions(runs: list[Run], seeds: set[int] | None = None) -> list[Effect]:
    """The paper's three conclusions as paired effects on the tracks ``seeds`` (None: all).

    1. With recent experience only, PPO (linear) beats each SPG variant: PPO - SPG > 0.
    2. With experience replay, each SPG cell beats the best PPO cell (among the PPO cells none
       of whose runs diverged, the one with the highest mean on these tracks, chosen on the same
       data): SPG - best PPO > 0.
    3. Prioritisation steadies SPG: SD over tracks of SPG-p minus that of SPG, per pair of
       cells (same epochs and replay mode), < 0.
    """
    effects = []
    ppo = finals_by_track(runs, "recent", "ppo", seeds)
    for algo in ("spg", "spg_multi", "spg_p", "spg_p_multi"):
        value, low, high, n = paired_bootstrap(ppo, finals_by_track(runs, "recent", algo, seeds), _mean_difference)
        effects.append(Effect("PPO beats SPG with recent experience only",
                              f"PPO linear - {COLUMN_TITLES[algo]} (recent)", value, low, high, n))
    ppo_cells = [(er, algo) for er in ER_ROWS for algo in ("ppo", "ppo_log")]

    def finished(key):  # the cell's runs on these tracks, if none of them diverged
        mine = [r for r in runs if (r.er, r.algo) == key and (seeds is None or r.seed in seeds)]
        return finals_by_track(runs, *key, seeds) if all(r.status == "completed" for r in mine) else {}

    scored = [(sum(v.values()) / len(v), key) for key in ppo_cells if (v := finished(key))]
    if scored:
        best = max(scored)[1]
        best_finals = finals_by_track(runs, *best, seeds)
        for er in ("memory", "hybrid"):
            for algo in ("spg", "spg_multi", "spg_p", "spg_p_multi"):
                value, low, high, n = paired_bootstrap(finals_by_track(runs, er, algo, seeds), best_finals,
                                                       _mean_difference)
                effects.append(Effect("SPG with experience replay beats the best PPO",
                                      f"{COLUMN_TITLES[algo]} ({er}) - {COLUMN_TITLES[best[1]]} ({best[0]})",
                                      value, low, high, n))
    for er in ER_ROWS:
        for plain, prioritised in SPG_PAIRS:
            value, low, high, n = paired_bootstrap(finals_by_track(runs, er, prioritised, seeds),
                                                   finals_by_track(runs, er, plain, seeds), _sd_difference)
            # the claim is a smaller spread: flip the sign so that "holds" means SD(SPG-p) < SD(SPG)
            effects.append(Effect("Prioritisation steadies SPG (smaller spread over tracks)",
                                  f"SD({COLUMN_TITLES[plain]}) - SD({COLUMN_TITLES[prioritised]}) ({er})",
                                  -value, -high, -low, n))
    return effects


def conclusions_markdown(runs: list[Run]) -> str:
    """The conclusions on the paper's five tracks and on every track of the sweep, side by side."""
    budgets = {r.budget for r in runs if r.status in ("completed", "diverged") and r.budget is not None}
    note = []
    if len(budgets) > 1:  # an effect pairs runs of one budget: the paper's if there are such runs, else the most common
        counts = {b: sum(r.budget == b for r in runs) for b in budgets}
        chosen = PAPER_EPISODES if PAPER_EPISODES in budgets else max(budgets, key=lambda b: (counts[b], b))
        left = sum(r.budget != chosen for r in runs if r.status in ("completed", "diverged"))
        runs = [r for r in runs if r.budget == chosen]
        note = [f"The effects pair runs of {chosen} episodes only: {left} finished run(s) of other budgets "
                f"({', '.join(str(b) for b in sorted(budgets - {chosen}))} episodes) are left out.", ""]
    all_seeds = {r.seed for r in runs if r.seed is not None}
    paper = set(PAPER_SEEDS) & all_seeds
    sets = [("paper tracks", paper)] if paper else []
    if all_seeds - paper:
        sets.append((f"all {len(all_seeds)} tracks", all_seeds))
    results = [(name, conclusions(runs, seeds)) for name, seeds in sets]
    if not results:
        return ""
    lines = note + ["Each effect is a mean (or SD) difference between two cells paired by track; the 95% "
             "interval is a percentile bootstrap over tracks (10,000 resamples). Verdict: holds if "
             "the interval lies above 0, reversed if below, undecided otherwise; no verdict on fewer than "
             f"{MIN_VERDICT_TRACKS} tracks (there the interval's ends are the extreme tracks). Tracks where a "
             "cell's run diverged are left out of that comparison.", ""]
    header = "| claim | effect | " + " | ".join(f"{name}: effect [95% CI] (n) | verdict" for name, _ in results) + " |"
    lines += [header, "|---|---|" + "---|---|" * len(results)]
    for i, effect in enumerate(results[0][1]):
        cells_text = []
        for _, effects in results:
            e = effects[i]
            if e.tracks == 0 or math.isnan(e.value):
                why = "no track where both cells finished" if e.tracks == 0 else "a spread needs two tracks"
                cells_text += [f"n/a: {why} ({e.tracks})", e.verdict]
                continue
            ci = f" [{e.low:+.1f}, {e.high:+.1f}]" if not math.isnan(e.low) else " [n/a: one track]"
            cells_text += [f"{e.value:+.1f}{ci} ({e.tracks})", e.verdict]
        lines.append(f"| {effect.claim} | {effect.label} | " + " | ".join(cells_text) + " |")
    return "\n".join(lines) + "\n"


def collapse_markdown(runs: list[Run]) -> str:
    """Per cell: runs whose final performance is below ``COLLAPSE_BELOW`` (collapsed), and diverged."""
    lines = [f"| cell | runs | collapsed (final < {COLLAPSE_BELOW:g}) | rate | diverged | collapsed tracks |",
             "|---|---:|---:|---:|---:|---|"]
    for er in ER_ROWS:
        for algo in ALGO_COLUMNS:
            mine = [r for r in runs if (r.er, r.algo) == (er, algo) and r.status in ("completed", "diverged")]
            if not mine:
                continue
            done = [r for r in mine if r.status == "completed" and r.final_mean is not None]
            low = sorted((r for r in done if r.final_mean < COLLAPSE_BELOW), key=lambda r: r.seed)
            rate = f"{len(low) / len(done):.0%}" if done else ""
            tracks = ", ".join(f"{r.seed} ({r.final_mean:.1f})" for r in low)
            lines.append(f"| {er} / {COLUMN_TITLES[algo]} | {len(done)} | {len(low)} | {rate} | "
                         f"{len(mine) - len(done)} | {tracks} |")
    return "\n".join(lines + budgets_note(runs)) + "\n"


def budgets_note(runs: list[Run]) -> list[str]:
    """The lines under a per-run table whose finished runs were trained for different budgets (none when
    they share one): which cells hold which budgets, since a short run's final is not a long run's."""
    done = [r for r in runs if r.status in ("completed", "diverged") and r.budget is not None]
    budgets = sorted({r.budget for r in done}, reverse=True)
    if len(budgets) < 2:
        return []
    parts = []
    for budget in budgets:
        cells = sorted({f"{r.er} / {ALGO_TITLES.get(r.algo, r.algo)}" for r in done if r.budget == budget})
        count = sum(r.budget == budget for r in done)
        parts.append(f"{budget} episodes: {count} run{'s' * (count > 1)} ({', '.join(cells)})")
    return ["", f"Note: these runs were trained for different budgets ({'; '.join(parts)}); a run's final "
                "after fewer episodes is not comparable with one after more, nor is its collapse."]


def normalised_markdown(runs: list[Run], oracle: dict[int, float]) -> str:
    """Per cell: final performance on the oracle's scale (0 = standing still, 1 = the oracle on the
    run's track), mean ± SE and median over the runs whose track the oracle scored; "" if none."""
    scored = [r for r in runs if r.status == "completed" and normalised(r, oracle) is not None]
    if not scored:
        return ""
    lines = ["Final performance on the oracle's scale of each run's track (0: a car that stands still, 1: "
             "the oracle, `evaluate.py --oracle`), over the runs whose track the oracle scored.", "",
             "| cell | runs | normalised (mean ± SE) | median | lowest | highest |", "|---|---:|---:|---:|---:|---:|"]
    cells_seen = sorted({(r.er, r.algo) for r in scored},
                        key=lambda c: (ER_ROWS.index(c[0]) if c[0] in ER_ROWS else 99,
                                       ALGO_COLUMNS.index(c[1]) if c[1] in ALGO_COLUMNS else 99, c))
    for er, algo in cells_seen:
        values = sorted(normalised(r, oracle) for r in scored if (r.er, r.algo) == (er, algo))
        mean = statistics.fmean(values)
        spread = (f"± {statistics.stdev(values) / math.sqrt(len(values)):.3f}" if len(values) > 1
                  else "(n/a: one run)")  # a standard error needs two runs
        lines.append(f"| {markdown_cell(er)} / {markdown_cell(ALGO_TITLES.get(algo, algo))} | {len(values)} | {mean:.3f} {spread} | "
                     f"{statistics.median(values):.3f} | {values[0]:.3f} | {values[-1]:.3f} |")
    tracks = sorted({r.seed for r in scored})
    lines += ["", f"Oracle scores used ({len(tracks)} tracks): "
              + ", ".join(f"{t}: {oracle[t]:.1f}" for t in tracks) + "."]
    return "\n".join(lines + budgets_note(scored)) + "\n"
