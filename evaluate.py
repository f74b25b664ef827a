"""Evaluate a trained run's deterministic policy and film it:

    python evaluate.py RUN_DIR [--tracks 2067791 773203] [--episodes 5] [--video agent.gif]

RUN_DIR is a finished train.py run folder (summary.json and actor.pt). The policy acts with
its mean action (no exploration). Prints the mean total reward per track; ``--video`` writes
one episode on the first track as a GIF or MP4 (needs the ``render`` extra).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from experiment.evaluate import RunFolderError, evaluate, film, load_policy


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--tracks", type=int, nargs="+", default=None,
                        help="track seeds (default: the run's own track)")
    parser.add_argument("--episodes", type=int, default=5, help="episodes per track (start states vary)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the start states")
    parser.add_argument("--video", type=Path, default=None, help="write one episode to this .gif or .mp4")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    try:
        net, settings = load_policy(args.run_dir)
    except RunFolderError as err:
        print(f"evaluate: {err}", file=sys.stderr)
        return 2
    tracks = args.tracks or [settings["seed"]]
    results = evaluate(net, settings, tracks, args.episodes, args.seed)
    for track, mean in results.items():
        print(f"track {track}: mean total reward {mean:.1f} over {args.episodes} episodes")
    if args.video is not None:
        try:
            frames = film(net, settings, tracks[0], args.video, args.seed)
        except (RuntimeError, ValueError) as err:
            print(f"evaluate: {err}", file=sys.stderr)
            return 2
        print(f"wrote {args.video} ({frames} frames)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
