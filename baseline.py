"""Outside reference learners: Stable-Baselines3's SAC and PPO with their defaults, one run per track:

    python baseline.py --algos sac ppo --tracks 2067791 5468063 [--episodes 201] [--jobs 2]
                       [--out outputs/sweeps/sb3] [--random-tracks]

Each run writes ``<out>/sb3_<algo>/default/seed<track>/`` (``metrics.csv``, ``summary.json``,
``model.zip``), which ``report.py`` reads like a ``train.py`` run; finished runs of the same
settings are skipped, a finished run of other settings or a damaged folder is refused (the folder
rules of ``engine/rundir.py``). ``--random-tracks`` trains on a new random track every episode (the
benchmark's protocol, docs/benchmark.md; the seeds then seed the runs). ``--jobs`` runs that many at once, one process each (one torch thread
per run). Needs the ``baselines`` extra (``pip install -c constraints/cpu.txt -e '.[baselines]'``).
What a run is, exactly: ``external/sb3.py``.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

from engine.budget import EPISODES, PROCESSES, SEED, check_items
from engine import numerics
from engine.outputs import RunFolderError
from engine.pool import run_jobs
from external.sb3 import ALGOS, BaselineError, run_folder, settings_of, train


def _train(args: tuple) -> dict:
    return train(*args)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algos", nargs="+", default=list(ALGOS), help=f"of {', '.join(ALGOS)}")
    parser.add_argument("--tracks", type=SEED, nargs="+", required=True, help="track seeds, one run each")
    parser.add_argument("--episodes", type=EPISODES, default=201)
    parser.add_argument("--final-window", type=EPISODES, default=20)
    parser.add_argument("--jobs", type=PROCESSES, default=1, help="runs at once, one process each")
    # Stable-Baselines3's networks are torch's own layers: their products are MKL's, never the
    # project's kernels, so numerics=fma would misname what runs; portable is its exact equivalent.
    parser.add_argument("--numerics", choices=[m for m in numerics.MODES if m != "fma"], default="portable",
                        help="portable (default: the same numbers on every AVX2 CPU) or native")
    parser.add_argument("--out", type=Path, default=Path("outputs/sweeps/sb3"))
    parser.add_argument("--random-tracks", action="store_true",
                        help="a new random track every episode (the benchmark's training; --tracks then only seed the runs)")
    args = parser.parse_args(argv)
    check_items(parser, "--tracks", args.tracks, 1_000, unique=True)  # one folder a track: two jobs would share it
    check_items(parser, "--algos", args.algos, len(ALGOS), unique=True)
    from engine.tool_output import check_output_folder

    check_output_folder(parser, "--out", args.out)  # its runs' folders go there: never inside another run's
    if importlib.util.find_spec("stable_baselines3") is None:
        print("baseline.py needs Stable-Baselines3: pip install -c constraints/cpu.txt -e '.[baselines]'",
              file=sys.stderr)
        return 2
    try:
        for algo in args.algos:
            for seed in args.tracks:
                settings_of(algo, seed, args.episodes, args.final_window, args.numerics, args.random_tracks)
        if args.jobs < 1:
            raise BaselineError(f"--jobs must be at least 1, got {args.jobs}")
        numerics.apply(args.numerics)
    except (BaselineError, numerics.NumericsError) as err:
        print(f"Refusing to run: {err}", file=sys.stderr)
        return 2
    work = [(algo, seed, args.episodes, args.out, args.final_window, args.numerics, args.random_tracks)
            for algo in args.algos for seed in args.tracks]
    try:
        summaries = run_jobs(_train, work, args.jobs, args.numerics)
    except (BaselineError, RunFolderError) as err:  # a damaged or busy folder, a run of other settings
        print(f"Refusing to run: {err}", file=sys.stderr)
        return 2
    for (algo, seed, *_), summary in zip(work, summaries):
        print(f"{run_folder(args.out, algo, seed)}: {summary['status']}, final_mean {summary['final_mean']:.2f}, "
              f"{summary['wall_time_s'] / 60:.1f} min")
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("baseline", main))
