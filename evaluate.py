"""Evaluate trained runs' deterministic policies, and film one:

    python evaluate.py RUN_DIR [--tracks 2067791 773203] [--episodes 5] [--video agent.gif]
    python evaluate.py SWEEP_DIR [RUN_DIR ...] [--tracks ...] [--table evaluation.csv]

    python evaluate.py --oracle --tracks 2067791 773203 [--episodes 5] [--table oracle.csv]

    python evaluate.py AGENT --video agent.gif [--tracks 2067791 | --track-file racing/tracks/oval.csv]
                       [--track-scale S] [--track-closed | --track-open]

A RUN_DIR is a finished train.py run folder (summary.json and actor.pt); any other folder
stands for every finished run inside it (a sweep, a population). Policies act without
exploration noise (the Gaussian's mean; SAC: tanh of it; TD3: its actor). Each run is evaluated
on its own track and on ``--tracks``; the table (printed, and written as CSV with ``--table``)
has one row per run and track. ``--video`` films one episode of the first run on its own track
as a GIF or MP4 (needs the ``render`` extra), and says which track and what total reward. Policies run under the numerics mode their runs
were trained in (``--numerics`` to choose another; ``engine/numerics.py``).

An AGENT that is not a run folder (``oracle``, ``pure_pursuit``, ``ray_follower``, a
Stable-Baselines3 ``model.zip`` or ``module:function``; ``score.py`` scores them) is filmed with
``--video``, on the first of ``--tracks`` (default: the first benchmark track) or on a track file.

``--oracle`` scores the planning controller ``racing.oracle.Oracle`` (it sees the simulator's
true state: a ceiling per track, not a policy) on ``--tracks`` with the same protocol;
``--candidates``, ``--horizon`` and ``--iterations`` set its planning budget.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from engine.budget import EPISODES, SEED, check_items, check_work, count
from engine import numerics
from engine.outputs import RunFolderError
from engine.rundir import runs_numerics
from engine.runset import read_runs
from racing.track_file import add_track_options


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", type=Path, nargs="*", metavar="RUN_OR_SWEEP_DIR")
    parser.add_argument("--tracks", type=SEED, nargs="+", default=[],
                        help="track seeds to evaluate on, besides each run's own track")
    parser.add_argument("--episodes", type=EPISODES, default=5, help="episodes per track (start states vary)")
    parser.add_argument("--seed", type=SEED, default=0, help="seed of the first start state")
    parser.add_argument("--table", type=Path, default=None, help="write the table to this CSV file")
    parser.add_argument("--video", type=Path, default=None, help="film the first run on its own track (.gif/.mp4)")
    parser.add_argument("--track-file", default=None,
                        help="with --video and an agent (not a run folder): film it on this track file")
    add_track_options(parser)
    parser.add_argument("--numerics", choices=numerics.MODES, default=None,
                        help="the numerics mode to evaluate in (default: the one the runs were trained in)")
    oracle = parser.add_argument_group("the oracle (a planning controller with the true state)")
    oracle.add_argument("--oracle", action="store_true", help="score the oracle on --tracks instead of runs")
    oracle.add_argument("--candidates", type=count(1, 100_000), default=None, help="action sequences per planning round")
    oracle.add_argument("--horizon", type=count(1, 1000), default=None, help="steps planned ahead")
    oracle.add_argument("--iterations", type=count(1, 1000), default=None, help="cross-entropy rounds per step")
    args = parser.parse_args(argv)
    check_items(parser, "--tracks", args.tracks, 10_000)
    check_work(parser, 1_000_000, "episodes", episodes=args.episodes, tracks=max(len(args.tracks), 1))
    check_work(parser, 10_000_000, "simulated steps a decision", candidates=args.candidates or 1,
               horizon=args.horizon or 1, iterations=args.iterations or 1)
    if args.video is not None and args.video.suffix.lower() not in (".gif", ".mp4"):
        parser.error(f"--video must name a .gif or .mp4 file, got {str(args.video)!r}")
    for option, path in (("--table", args.table), ("--video", args.video)):
        if path is not None and path.is_dir():
            parser.error(f"{option} {path} is a folder; give a file name (e.g. {path / ('evaluation.csv' if option == '--table' else 'agent.gif')})")
    from engine.processes import check_start_seeds
    from engine.tool_output import check_outputs  # before any episode: not after the work

    check_start_seeds(parser, args.seed, args.episodes)

    check_outputs(parser, reads=[*args.paths, *([args.track_file] if args.track_file else [])], table=args.table,
                  video=args.video)
    if args.track_file is not None:
        from racing.track_file import TrackFileError, parse_track

        try:
            args.track_file = parse_track("--track-file", args.track_file, args.track_scale, args.track_closed)
        except TrackFileError as err:
            parser.error(str(err))
    elif args.track_scale is not None or args.track_closed is not None:
        parser.error("--track-scale, --track-closed and --track-open apply to --track-file")
    if args.oracle:
        if args.paths or not args.tracks:
            parser.error("--oracle scores the oracle on --tracks (give track seeds, and no run folders)")
        return _oracle(args)
    if not args.paths:
        parser.error("give run or sweep folders to evaluate (or --oracle --tracks ...)")
    agents = [p for p in args.paths if not p.is_dir()]
    if agents and args.video is not None and len(agents) == len(args.paths) == 1:
        return _film_agent(str(agents[0]), args)  # any agent filmed: the oracle, a driver, a model.zip, ...
    try:
        runs = read_runs(args.paths, say="evaluate").runs
        numerics.apply(args.numerics or runs_numerics(runs, "--numerics"))  # before torch loads
    except (RunFolderError, numerics.NumericsError) as err:
        print(f"evaluate: {err}", file=sys.stderr)
        return 2
    from engine.evaluation import evaluate, film, load_policy, own_track

    rows, skipped, first = [], [], None
    for run in runs:
        try:
            policy, settings = load_policy(run)
        except RunFolderError as err:
            if len(runs) == 1:
                print(f"evaluate: {err}", file=sys.stderr)
                return 2
            skipped.append(f"{run}: {err}")  # e.g. a diverged run of a sweep: no actor to evaluate
            continue
        own = own_track(settings)
        tracks = [own, *[t for t in args.tracks if t != own]]
        results = evaluate(policy, settings, tracks, args.episodes, args.seed)
        for track, mean in results.items():
            rows.append({"run": str(run), "algo": settings["algo"]["name"], "er": settings["er"]["name"],
                         "train_seed": settings["seed"], "train_tracks": settings["env"]["track"], "track": track,
                         "own_track": track == own, "episodes": args.episodes, "mean_reward": round(mean, 6)})
        if first is None:
            first = (policy, settings, tracks, run)
    _print(rows, len(runs) > 1)
    for line in skipped:
        print(f"skipped {line}", file=sys.stderr)
    if args.table is not None and rows:
        _write_table(args.table, rows)
    if args.video is not None and first is not None:
        policy, settings, tracks, run = first
        track = tracks[0]  # the run's own: the first of the evaluated tracks
        try:
            frames, total = film(policy, settings, track, args.video, args.seed, name=str(run))
        except (RuntimeError, ValueError) as err:
            print(f"evaluate: {err}", file=sys.stderr)
            return 2
        print(f"track {track} (its own): {run} drove to a total reward of {total:.1f}; wrote {args.video} "
              f"({frames} frames)")
    return 0 if rows else 2


def _film_agent(spec: str, args) -> int:
    """``--video`` of an agent that is not a run folder (``score.py``'s kinds: ``oracle``,
    ``pure_pursuit``, ``ray_follower``, a Stable-Baselines3 ``model.zip``, ``module:function``) on
    the first of ``--tracks`` (default: the first benchmark track) or on ``--track-file``."""
    numerics.apply(args.numerics or numerics.DEFAULT)
    from benchmark.protocol import TRACKS, AgentError, film, load_agent

    try:
        agent = load_agent(spec)
        track = args.track_file if args.track_file is not None else (args.tracks or [TRACKS[0]])[0]
        frames, total = film(agent, track, args.video, args.seed)
    except (AgentError, RuntimeError, ValueError, TypeError) as err:
        print(f"evaluate: {err}", file=sys.stderr)
        return 2
    print(f"track {track}: {agent.name} drove to a total reward of {total:.1f}; wrote {args.video} ({frames} frames)")
    return 0


def _oracle(args) -> int:
    import dataclasses

    from racing.oracle import OracleSettings, score

    from engine.version import code_version

    code = code_version()  # before the work: the code that computes it
    budget = {k: getattr(args, k) for k in ("candidates", "horizon", "iterations") if getattr(args, k) is not None}
    try:
        settings = dataclasses.replace(OracleSettings(), **budget)
        results = score(args.tracks, args.episodes, args.seed, settings)
    except (TypeError, ValueError) as err:
        print(f"evaluate: {err}", file=sys.stderr)
        return 2
    rows = []
    for track, result in results.items():
        print(f"track {track}: oracle mean total reward {result['mean']:.1f} over {args.episodes} episodes "
              f"({result['seconds_per_episode']:.1f} s per episode)")
        rows.append({"run": "oracle", "algo": "oracle", "track": track, "episodes": args.episodes,
                     "mean_reward": round(result["mean"], 6),
                     "seconds_per_episode": round(result["seconds_per_episode"], 3),
                     **dataclasses.asdict(settings), "commit": code.get("commit") or "", "dirty": code.get("dirty"),
                     "source": code["source"]})
    if args.table is not None:
        _write_table(args.table, rows)
    return 0


def _write_table(path: Path, rows: list[dict]) -> None:
    from engine.outputs import write_table

    write_table(path, rows)


def _print(rows: list[dict], several: bool) -> None:
    if not several:
        for row in rows:
            print(f"track {row['track']}: mean total reward {row['mean_reward']:.1f} over {row['episodes']} episodes"
                  + (" (its own track)" if row["own_track"] else ""))
        return
    print("| run | own track | other tracks (mean) |\n|---|---:|---:|")
    by_run: dict[str, list[dict]] = {}
    for row in rows:
        by_run.setdefault(row["run"], []).append(row)
    for run, items in by_run.items():
        own = next(r["mean_reward"] for r in items if r["own_track"])
        others = [r["mean_reward"] for r in items if not r["own_track"]]
        print(f"| {run} | {own:.1f} | {math.fsum(others) / len(others):.1f} |" if others else f"| {run} | {own:.1f} | |")


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("evaluate", main))
