"""The oracle's memory and time on a long circuit beside a generated track.

    python -m speed.oracle_circuit [--points 1200] [--steps 100] [FILE ...]

For each track (a generated track, seed 1001; a circuit of ``--points`` checkpoints in a
downloaded TUM file's layout, made by ``racing.track_file.make_circuit`` and read by the same
rules; any track FILE given), in a fresh process: the start-up (the environment built, the
``Oracle`` built and its first action planned, as ``drive.py`` and ``score.py`` pay it), the
seconds per step over ``--steps`` steps after that, and the process's peak memory (its maximum
resident set). The last column is each track's time per step over the generated track's,
measured in the same run.
"""

from __future__ import annotations

from engine.budget import STEPS, count
import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

MEASURE = """
import json, resource, sys, time
start = time.perf_counter()
from racing.gym_env import RacingEnv
from racing.oracle import Oracle
track, steps = sys.argv[1], int(sys.argv[2])
where = {"track_seed": int(track)} if track.isdigit() else {"track_file": track}
env = RacingEnv(max_steps=steps + 1, **where)
env.reset(seed=0)
oracle = Oracle(seed=0)
sim = env.unwrapped.sim
env.step(oracle.act(sim, 0))
ready = time.perf_counter()
for _ in range(steps):
    env.step(oracle.act(sim, 0))
done = time.perf_counter()
print(json.dumps({"checkpoints": env.config.num_segments, "startup_s": ready - start,
                  "step_s": (done - ready) / steps, "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def measure(track: str, steps: int) -> dict:
    """One track's start-up, time per step and peak memory, in a fresh Python process."""
    root = Path(__file__).resolve().parent.parent
    result = subprocess.run([sys.executable, "-c", MEASURE, track, str(steps)], cwd=root, capture_output=True,
                            text=True, check=False)
    if result.returncode != 0:
        raise SystemExit(f"oracle_circuit: measuring {track} failed:\n{result.stderr[-2000:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="*", metavar="FILE", help="more track files to measure")
    parser.add_argument("--points", type=count(3, 100_000), default=1200, help="checkpoints of the made circuit")
    parser.add_argument("--steps", type=STEPS, default=100, help="oracle steps timed per track")
    args = parser.parse_args(argv)
    if args.steps < 1 or not 3 <= args.points <= 5000:
        parser.error("--steps must be >= 1 and --points in [3, 5000]")
    from racing.track_file import make_circuit, write_rows

    with tempfile.TemporaryDirectory() as folder:
        circuit = write_rows(Path(folder) / f"circuit_{args.points}.csv", make_circuit(args.points))
        tracks = [("generated (seed 1001)", "1001"), (f"circuit ({args.points} points)", str(circuit))]
        tracks += [(Path(f).name, str(Path(f).resolve())) for f in args.files]
        rows = [(name, measure(track, args.steps)) for name, track in tracks]
    base = rows[0][1]["step_s"]
    print(f"oracle (racing.oracle.OracleSettings defaults), {args.steps} steps timed per track, one process each")
    print(f"{'track':<28} {'checkpoints':>11} {'start-up s':>10} {'ms/step':>8} {'peak MB':>8} {'step / generated':>16}")
    for name, r in rows:
        print(f"{name:<28} {r['checkpoints']:>11,} {r['startup_s']:>10.2f} {1000 * r['step_s']:>8.1f} "
              f"{r['peak_mb']:>8.0f} {r['step_s'] / base:>16.2f}")
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("speed.oracle_circuit", main))
