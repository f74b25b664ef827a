"""Track files (racing/track_file.py: the TUM racetrack-database's CSV columns): check one, draw
one, make a circuit, or export a generated track to one.

    python tracks.py check FILE [--track-scale S] [--track-closed | --track-open] [--no-lap]
    python tracks.py show FILE [--out track.png] [--track-scale S] [--track-closed | --track-open]
    python tracks.py circuit [--points 1200] [--out circuit.csv]
    python tracks.py export --seed 2067791 [--out track_2067791.csv]

``check`` loads the file as the environments do and prints what it holds: whether it is read as
a circuit and at which scale (and where each came from: the options, the file's comments, or
the rules for a downloaded file), the road's width, what the car may not fit, and how many
steps a lap (an open track: the way to the finish) takes the pure-pursuit driver and the ray
follower, the pace to size ``env.options.max_steps`` by; or the line and the problem that stops
it loading. ``show`` also draws it (the ``render`` extra). ``circuit`` writes a circuit in the
layout of a downloaded TUM file (metres, closed, no comments but the header); ``export`` writes
the track of a seed as a file. Train on a file with ``python train.py env.track=file
env.track_file=FILE``. Example files ship in ``racing/tracks/`` (``oval``, ``kidney``: circuits;
``paper_2067791``: the first paper track, exported).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from engine.budget import SEED, count
from racing.config import MAX_STEPS, RacingConfig
from racing.track import track_from_seed
from racing.track_file import (MAX_ROWS, TrackFileError, WallsCross, add_track_options, load_track, make_circuit,
                               save_track, write_rows)

STEP_SECONDS = 1 / 30  # racing.sim.RacingSim.STEP_SECONDS (not imported: check stays free of the simulator's tables)


def describe(track) -> str:
    """One line: the track's name, shape, checkpoints, length and road width."""
    widths = np.hypot(*(track.left_wall - track.right_wall).T)
    kind = "a circuit (closed)" if track.closed else "open (start to finish)"
    length = track.centre_line_length()
    return (f"{track.name}: {kind}, {track.num_checkpoints} checkpoints, centre line {length:,.0f} px, "
            f"road {widths.min():.0f} to {widths.max():.0f} px wide (median {np.median(widths):.0f})")


def reading_lines(track) -> list[str]:
    """How the file was read (shape, scale, where each came from) and its warnings."""
    r = track.reading
    lines = [f"  read as {'a circuit' if r.closed else 'open'} (from {r.closed_from}), scale {r.scale:g} px per "
             f"file unit (from {r.scale_from})"]
    return lines + [f"  warning: {w}" for w in r.warnings]


def lap(path: Path, scale, closed, track, driver: str) -> dict:
    """One lap of a circuit (an open track: the way to the finish), ``track`` as the file ``path``
    reads with ``scale`` and ``closed``, by a reference driver (``pure_pursuit`` or
    ``ray_follower``), with a step cap of 20 steps per 50 px of centre line: {"steps": ...,
    "crashes": ..., "done": whether it got round}."""
    from racing.driver import PurePursuit, ray_follower
    from racing.gym_env import RacingEnv

    cap = int(min(MAX_STEPS, 20 * track.centre_line_length() / RacingConfig().max_speed + 1_000))
    env = RacingEnv(track_file=str(path), track_scale=scale, track_closed=closed, max_steps=cap)
    obs, _ = env.reset(seed=0)
    sim, pursuit = env.unwrapped.sim, PurePursuit()
    for step in range(1, cap + 1):
        action = pursuit.act(sim, 0) if driver == "pure_pursuit" else ray_follower(obs)
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or (track.closed and sim.laps[0] >= 1):
            return {"steps": step, "crashes": int(sim.crashes[0]), "done": True}
        if truncated:
            break
    return {"steps": cap, "crashes": int(sim.crashes[0]), "done": False}


def lap_lines(path: Path, scale, closed, track) -> list[str]:
    what = "a lap" if track.closed else "the way to the finish"
    lines, paces = [], []
    for driver in ("pure_pursuit", "ray_follower"):
        result = lap(path, scale, closed, track, driver)
        if result["done"]:
            paces.append(result["steps"])
            lines.append(f"  {what}: {result['steps']:,} steps ({result['steps'] * STEP_SECONDS:.1f} s) for the "
                         f"{driver.replace('_', '-')} driver, {_crashes(result['crashes'])}")
        else:
            lines.append(f"  {what}: the {driver.replace('_', '-')} driver did not get round in {result['steps']:,} "
                         f"steps ({_crashes(result['crashes'])})")
    if paces:
        steps = int(np.ceil(max(paces) * 1.25 / 100) * 100)
        laps = " and env.options.laps=1 (the episode ends at the lap)" if track.closed else ""
        default, share = RacingConfig().max_steps, RacingConfig().max_steps / min(paces)
        cover = (f"{share:.2g} laps" if track.closed and share >= 1 else "all of it" if share >= 1
                 else f"{share:.0%} of " + ("a lap" if track.closed else "it"))
        lines.append(f"  {what} in one episode: env.options.max_steps={steps}{laps}; the default {default} steps "
                     f"cover {cover} at the faster driver's pace")
    return lines


def _crashes(n: int) -> str:
    return f"{n} crash" + ("" if n == 1 else "es")


FIGURE_SUFFIXES = (".png", ".pdf", ".svg", ".jpg")  # what the figures are written as (matplotlib's formats)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    for name in ("check", "show"):
        command = commands.add_parser(name, help="load a track file" + (" and draw it" if name == "show" else ""))
        command.add_argument("file", type=Path)
        add_track_options(command)
        if name == "check":
            command.add_argument("--no-lap", action="store_true", help="do not drive a lap with the reference drivers")
        if name == "show":
            command.add_argument("--out", type=Path, default=None, help="the figure (default: FILE with .png)")
    circuit = commands.add_parser("circuit", help="write a circuit in a downloaded TUM file's layout")
    circuit.add_argument("--points", type=count(3, MAX_ROWS), default=1200, help=f"centre-line points, 5 m apart (3 to {MAX_ROWS:,})")
    circuit.add_argument("--out", type=Path, default=Path("circuit.csv"))
    export = commands.add_parser("export", help="write a generated track as a file")
    export.add_argument("--seed", type=SEED, required=True, help="the track seed")
    export.add_argument("--out", type=Path, default=None, help="default: track_<seed>.csv")
    args = parser.parse_args(argv)
    from engine.tool_output import check_outputs

    check_outputs(parser, out=getattr(args, "out", None))
    if args.command == "show":
        out = args.out or args.file.with_suffix(".png")
        if out.suffix.lower() not in FIGURE_SUFFIXES:
            parser.error(f"--out must name a picture ({', '.join(FIGURE_SUFFIXES)}), got {str(out)!r}")
        if out.resolve() == args.file.resolve():
            parser.error(f"--out {out} is the track file itself; give the figure another name")
    if args.command == "export":
        path = save_track(track_from_seed(args.seed, RacingConfig()), args.out or Path(f"track_{args.seed}.csv"))
        try:
            track = load_track(path)
        except TrackFileError as err:
            from door import files

            files.remove(path)
            print(f"tracks: the track of seed {args.seed} cannot be a file: {err}", file=sys.stderr)
            return 2
        print(f"wrote {path}: {describe(track)}")
        return 0
    if args.command == "circuit":
        if args.out.is_dir():
            parser.error(f"--out {args.out} is a folder; give a file name (e.g. {args.out / 'circuit.csv'})")
        path = write_rows(args.out, make_circuit(args.points))
        print(f"wrote {path}: {describe(load_track(path))}")
        return 0
    try:
        track = load_track(args.file, args.track_scale, args.track_closed)
    except WallsCross as err:  # refused; shown anyway, so the crossing can be seen
        if args.command == "show":
            try:
                from racing.figures import track_file_figure

                drawn = track_file_figure(err.track, out, "refused: its walls cross (marked in red)", err.segments)
                print(f"wrote {drawn}: the refused track, its crossing marked in red")
            except ImportError:
                pass  # the refusal below says what matters
        print(f"tracks: {err}", file=sys.stderr)
        return 2
    except TrackFileError as err:
        print(f"tracks: {err}", file=sys.stderr)
        return 2
    print(describe(track))
    print("\n".join(reading_lines(track)))
    if args.command == "check" and not args.no_lap:
        print("\n".join(lap_lines(args.file, args.track_scale, args.track_closed, track)))
    if args.command == "show":
        try:
            from racing.figures import track_file_figure

            out = track_file_figure(track, out, describe(track))
        except ImportError as err:
            print(f"tracks: {err}", file=sys.stderr)
            return 2
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("tracks", main))
