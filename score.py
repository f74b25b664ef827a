"""Score any agent on the benchmark: ten fixed tracks nothing here was tuned on, five episodes
each from the same start states (benchmark/protocol.py; docs/benchmark.md):

    python score.py AGENT [AGENT ...] [--table scores.csv] [--episodes 5]
    python score.py AGENT --video agent.gif [--video-track SEED_OR_FILE] [--max-steps 400]
                    [--track-scale S] [--track-closed | --track-open]
    python score.py AGENT [AGENT ...] --laps-on CIRCUIT.csv [--laps 3] [--max-steps N] [--table laps.csv]

AGENT is a train.py run folder, a Stable-Baselines3 ``model.zip``, ``module:function`` (a
Python callable ``observation -> [throttle, steering]``, its module importable from here), or
one of ``oracle``, ``pure_pursuit``, ``ray_follower``. For each it prints the benchmark score
(the mean over tracks of the mean total reward per track) with its 95% interval over tracks, and
the oracle-normalised score (each track's score over the oracle's, shipped in
``analysis/data/oracle_benchmark.csv``) with its interval; ``--table`` writes every agent's
per-track scores as CSV. ``--episodes`` other than 5 is not the protocol, and says so.
``--video`` films one episode of each agent instead (its name, reward so far, progress, crashes,
on a circuit its laps, and a map of the whole track drawn on the frames; the ``render`` extra), on the
first benchmark track or ``--video-track``.
``--laps-on`` times laps instead: each agent drives a circuit (a track file, read by the rules of
racing/track_file.py or ``--track-scale``/``--track-closed``) from start seed 0 until ``--laps``
laps are done or a step cap is reached (``--max-steps``; default four times the steps its centre
line takes at full speed, per lap), and its laps, best lap (seconds, 30 steps a second),
crashes and total reward are printed (and written with ``--table``).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

from engine.budget import SEED, STEPS, check_items, check_work, count
from engine import numerics
from racing.track_file import add_track_options


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("agents", nargs="+", metavar="AGENT")
    parser.add_argument("--episodes", type=count(1, 100_000), default=None, help="episodes per track (the protocol: 5)")
    parser.add_argument("--tracks", type=SEED, nargs="+", default=None,
                        help="other track seeds (not the protocol: no oracle-normalised score unless shipped)")
    parser.add_argument("--table", type=Path, default=None, help="write per-track scores to this CSV file")
    parser.add_argument("--video", type=Path, default=None,
                        help="film one episode of each agent instead of scoring (.gif or .mp4; one agent: this "
                             "file; several: <stem>-<n><suffix>)")
    parser.add_argument("--video-track", default=None,
                        help="the track to film on: a seed or a track file (default: the first benchmark track)")
    parser.add_argument("--max-steps", type=STEPS, default=None,
                        help="the film's episode length (default 200); with --laps-on, the step cap")
    parser.add_argument("--laps-on", default=None, metavar="FILE",
                        help="time laps on this circuit (a track file) instead of scoring")
    parser.add_argument("--laps", type=count(1, 1000), default=None,
                        help="with --laps-on: laps per agent (default 3); with --video on a circuit: the film ends "
                             "after this many laps")
    add_track_options(parser)
    parser.add_argument("--numerics", choices=numerics.MODES, default=None,
                        help="the numerics to run run folders' policies in (default: the one they were trained in)")
    args = parser.parse_args(argv)
    check_items(parser, "AGENT", args.agents, 1_000)
    check_items(parser, "--tracks", args.tracks, 10_000)
    check_work(parser, 1_000_000, "episodes", agents=len(args.agents), tracks=len(args.tracks or [0] * 10),
               episodes=args.episodes or 5)
    if args.video is not None and args.video.suffix.lower() not in (".gif", ".mp4"):
        parser.error(f"--video must name a .gif or .mp4 file, got {str(args.video)!r}")
    if (args.laps is not None and args.laps < 1) or (args.max_steps is not None and args.max_steps < 1):
        parser.error("--laps and --max-steps must be at least 1")
    if args.laps_on is not None and args.video is not None:
        parser.error("give --laps-on or --video, not both")
    if args.laps_on is not None:
        circuit = _track(parser, args.laps_on, args.track_scale, args.track_closed, "--laps-on")
        if isinstance(circuit, int):
            parser.error(f"--laps-on needs a track file (a circuit), got the seed {circuit}")
        video_track = None
    else:
        video_track = _track(parser, args.video_track, args.track_scale, args.track_closed)
    from engine.tool_output import check_outputs  # before any episode: not after the work

    reads = [*args.agents, *(path for path in (args.laps_on, args.video_track) if path)]
    check_outputs(parser, reads=reads, table=None if args.table is None or args.table.is_dir() else args.table,
                  video=args.video)
    if args.table is not None and args.table.is_dir():
        parser.error(f"--table {args.table} is a folder; give a file name (e.g. {args.table / 'scores.csv'})")
    runs = [a for a in args.agents if os.path.lexists(Path(a) / "summary.json")]
    if runs:  # a run named twice, through a link, or copied is one agent (engine.runset), said in one line
        from engine.outputs import RunFolderError
        from engine.runset import read_runs

        try:
            distinct = read_runs(runs, say="score").runs
        except RunFolderError as err:
            print(f"score: {err}", file=sys.stderr)
            return 2
        standing, taken, kept = {os.path.realpath(p) for p in distinct}, set(), []
        for spec in args.agents:
            real = os.path.realpath(spec)
            if spec in runs and (real not in standing or real in taken):
                continue
            taken.add(real)
            kept.append(spec)
        args.agents = kept
    folders = [Path(a) for a in args.agents if Path(a).is_dir()]
    try:
        mode = args.numerics or (_runs_numerics(folders) if folders else numerics.DEFAULT)
        numerics.apply(mode)  # before torch loads
    except (ValueError, numerics.NumericsError) as err:
        print(f"score: {err}", file=sys.stderr)
        return 2
    from benchmark.protocol import EPISODES, TRACKS, AgentError, load_agent, read_oracle, score, summarise

    tracks = tuple(args.tracks) if args.tracks else TRACKS
    episodes = args.episodes or EPISODES
    try:
        agents = [load_agent(spec) for spec in args.agents]  # every agent checked before any is scored
    except AgentError as err:
        print(f"score: {err}", file=sys.stderr)
        return 2
    if args.video is not None:
        return _film(agents, args.video, video_track if video_track is not None else TRACKS[0], args.max_steps,
                     args.laps)
    if args.laps_on is not None:
        return _lap_times(agents, circuit, args.laps or 3, args.max_steps, args.table)
    if (tracks, episodes) != (TRACKS, EPISODES):
        print(f"note: {len(tracks)} tracks x {episodes} episodes is not the benchmark's protocol "
              f"({len(TRACKS)} x {EPISODES}); the scores are not comparable with docs/benchmark.md")
    oracle = read_oracle()
    rows = []
    for agent in agents:
        try:
            per_track = score(agent, tracks, episodes)
        except (ValueError, TypeError) as err:  # e.g. a callable returning a wrong action
            print(f"score: {agent.name}: {err}", file=sys.stderr)
            return 2
        summary = summarise(per_track, oracle)
        line = (f"{agent.name} ({agent.kind}): score {summary['mean']:.1f} {_interval(summary['ci'], 1)} over "
                f"{summary['tracks']} {'track' if summary['tracks'] == 1 else 'tracks'} x {episodes} episodes")
        if "normalised" in summary:
            line += f"; oracle-normalised {summary['normalised']:.3f} {_interval(summary['normalised_ci'], 3)}"
        print(line)
        rows += [{"agent": agent.name, "kind": agent.kind, "track": track, "episodes": episodes,
                  "mean_reward": round(value, 6), "oracle": oracle.get(track, ""),
                  "normalised": round(value / oracle[track], 6) if track in oracle else ""}
                 for track, value in per_track.items()]
    if args.table is not None:
        from engine.outputs import write_table

        write_table(args.table, rows)
    return 0


def _interval(bounds, digits: int) -> str:
    """A 95% interval over tracks as printed: "n/a" where one track gives none."""
    low, high = bounds
    if not (math.isfinite(low) and math.isfinite(high)):
        return "[n/a: one track]"
    return f"[{low:.{digits}f}, {high:.{digits}f}]"


def _track(parser, text: str | None, scale: float | None, closed: bool | None, option: str = "--video-track"):
    """--video-track or --laps-on: a seed, or a track file (checked now) with --track-scale/--track-closed."""
    from racing.track_file import TrackFileError, parse_track

    if text is None and (scale is not None or closed is not None):
        parser.error("--track-scale, --track-closed and --track-open apply to a --video-track or --laps-on file")
    try:
        return None if text is None else parse_track(option, text, scale, closed)
    except TrackFileError as err:
        parser.error(str(err))


def _film(agents, path: Path, track, max_steps: int | None, laps: int | None = None) -> int:
    from benchmark.protocol import film

    options = {**({} if max_steps is None else {"max_steps": max_steps}),
               **({} if laps is None else {"laps": laps})}  # laps on a track that is not a circuit: the sim refuses
    for n, agent in enumerate(agents):
        out = path if len(agents) == 1 else path.with_name(f"{path.stem}-{n}{path.suffix}")
        try:
            frames, total = film(agent, track, out, **options)
        except (RuntimeError, ValueError, TypeError) as err:
            print(f"score: {agent.name}: {err}", file=sys.stderr)
            return 2
        print(f"wrote {out}: {agent.name} on track {track}, {frames} frames ({out.stat().st_size / 1e6:.1f} MB), "
              f"total reward {total:.1f}")
    return 0


def _lap_times(agents, circuit, laps: int, max_steps: int | None, table: Path | None) -> int:
    from benchmark.protocol import lap_times

    rows = []
    for agent in agents:
        try:
            result = lap_times(agent, circuit, laps, max_steps=max_steps)
        except (RuntimeError, ValueError, TypeError) as err:
            print(f"score: {agent.name}: {err}", file=sys.stderr)
            return 2
        best = "no lap" if result["best_lap_s"] is None else f"best lap {result['best_lap_s']:.2f} s"
        each = ", ".join(f"{s:.2f}" for s in result["lap_seconds"])
        capped = " (the step cap)" if result["laps"] < laps else ""
        crashes = f"{result['crashes']} crash" + ("" if result["crashes"] == 1 else "es")
        print(f"{Path(str(circuit)).name}: {agent.name}: {result['laps']} of {laps} laps in {result['steps']:,} steps"
              f"{capped}, {best}" + (f" (laps {each} s)" if each else "") + f", {crashes}, total reward "
              f"{result['total_reward']:.1f}")
        rows.append({"agent": agent.name, "kind": agent.kind, "circuit": str(circuit), "laps": result["laps"],
                     "best_lap_s": result["best_lap_s"] if result["best_lap_s"] is not None else "",
                     "lap_seconds": " ".join(f"{s:.3f}" for s in result["lap_seconds"]),
                     "crashes": result["crashes"], "steps": result["steps"],
                     "total_reward": round(result["total_reward"], 6)})
    if table is not None:
        from engine.outputs import write_table

        write_table(table, rows)
    return 0


def _runs_numerics(folders: list[Path]) -> str:
    from engine.rundir import runs_numerics

    return runs_numerics(folders, "--numerics")


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("score", main))
