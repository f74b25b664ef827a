"""Drive the hand-written ray follower for one episode on a paper track and write pictures.

    python demo.py [--track-seed 2067791] [--out outputs/demo]

Writes ``trajectory.png`` (the whole track with the car's path), ``car.png`` (the
following camera with the five rays, like the paper's screenshot) and ``paper_tracks.png``
(the five paper tracks, like the paper's Figure 1).
"""

from __future__ import annotations

import argparse
import io
import os
from pathlib import Path

import numpy as np

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # draw without a screen

from door import files  # noqa: E402
from engine.budget import SEED
from racing import PAPER_TRACK_SEEDS, RacingEnv  # noqa: E402
from racing.driver import ray_follower  # noqa: E402
from racing.figures import tracks_figure  # noqa: E402
from racing.render import import_pygame, track_view  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--track-seed", type=SEED, default=PAPER_TRACK_SEEDS[0])
    parser.add_argument("--seed", type=SEED, default=0, help="seed of the start state")
    parser.add_argument("--out", type=Path, default=Path("outputs/demo"))
    args = parser.parse_args()
    files.folder(args.out, args.out, create=True)

    env = RacingEnv(track_seed=args.track_seed, render_mode="rgb_array")
    obs, info = env.reset(seed=args.seed)
    trail, total, crashes = [(info["x"], info["y"])], 0.0, 0
    done = False
    while not done:
        obs, reward, terminated, truncated, info = env.step(ray_follower(obs))
        trail.append((info["x"], info["y"]))
        total += reward
        crashes += info["crashed"]
        done = terminated or truncated
    print(f"track {args.track_seed}: return {total:.1f} in {info['step']} steps, "
          f"{crashes} crashes, checkpoint {info['checkpoint']}/{env.config.num_segments}")

    pg = import_pygame()
    canvas = track_view(env.track, size=(900, 700))
    canvas.trail(np.array(trail))
    canvas.car(info["x"], info["y"], info["theta"], obs, env.config)
    for name, surface in (("trajectory.png", canvas.surface),
                          ("car.png", pg.surfarray.make_surface(env.render().transpose(1, 0, 2)))):
        buffer = io.BytesIO()
        pg.image.save(surface, buffer, name)  # encoded in memory, written whole through the file door
        files.write_atomic(args.out / name, buffer.getvalue())
    tracks_figure(args.out / "paper_tracks.png")
    env.close()
    print(f"pictures written to {args.out}/: trajectory.png, car.png, paper_tracks.png")
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("demo", main))
