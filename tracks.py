"""Track files (racing/track_file.py: the TUM racetrack-database's CSV columns): check one, draw
one, or export a generated track to one.

    python tracks.py check FILE [--scale S] [--closed | --open]
    python tracks.py show FILE [--out track.png] [--scale S] [--closed | --open]
    python tracks.py export --seed 2067791 [--out track_2067791.csv]

``check`` loads the file as the environments do and prints what it holds (or the line and the
problem that stops it loading); ``show`` also draws it (the ``render`` extra); ``export`` writes
the track of a seed as a file. Train on a file with ``python train.py env.track=file
env.track_file=FILE``; drive on one with ``gym.make("racing/Racing-v0", track_file=FILE)``.
Example files ship in ``racing/tracks/`` (``oval``, ``kidney``: circuits; ``paper_2067791``:
the first paper track, exported).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from racing.config import RacingConfig
from racing.track import track_from_seed
from racing.track_file import TrackFileError, load_track, save_track


def describe(track) -> str:
    centre = (track.left_wall + track.right_wall) / 2
    length = float(np.hypot(*np.diff(centre, axis=0).T).sum())
    widths = np.hypot(*(track.left_wall - track.right_wall).T)
    kind = "a circuit (closed)" if track.closed else "open (start to finish)"
    return (f"{track.name}: {kind}, {track.num_checkpoints} checkpoints, centre line {length:,.0f} px, "
            f"width {widths.min():.0f} to {widths.max():.0f} px")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    for name in ("check", "show"):
        command = commands.add_parser(name, help="load a track file" + (" and draw it" if name == "show" else ""))
        command.add_argument("file", type=Path)
        command.add_argument("--scale", type=float, default=None, help="pixels per file unit (default: the file's)")
        shape = command.add_mutually_exclusive_group()
        shape.add_argument("--closed", dest="closed", action="store_const", const=True, default=None)
        shape.add_argument("--open", dest="closed", action="store_const", const=False)
        if name == "show":
            command.add_argument("--out", type=Path, default=None, help="the figure (default: FILE with .png)")
    export = commands.add_parser("export", help="write a generated track as a file")
    export.add_argument("--seed", type=int, required=True, help="the track seed")
    export.add_argument("--out", type=Path, default=None, help="default: track_<seed>.csv")
    args = parser.parse_args(argv)
    if args.command == "export":
        if not 0 <= args.seed < 2**32:
            parser.error(f"--seed must be in [0, 2**32), got {args.seed}")
        path = save_track(track_from_seed(args.seed, RacingConfig()), args.out or Path(f"track_{args.seed}.csv"))
        try:
            track = load_track(path)
        except TrackFileError as err:
            path.unlink()
            print(f"tracks: the track of seed {args.seed} cannot be a file: {err}", file=sys.stderr)
            return 2
        print(f"wrote {path}: {describe(track)}")
        return 0
    try:
        track = load_track(args.file, args.scale, args.closed)
    except TrackFileError as err:
        print(f"tracks: {err}", file=sys.stderr)
        return 2
    print(describe(track))
    if args.command == "show":
        from racing.figures import track_file_figure

        out = args.out or args.file.with_suffix(".png")
        print(f"wrote {track_file_figure(track, out, describe(track))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
