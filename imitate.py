"""The reactive ceiling (docs/beyond.md): an actor network that sees only the observation, taught
by the oracle itself with DAgger (pupil/dagger.py), scored with the usual protocol:

    python imitate.py --tracks 1001 1002 1003 [--hidden 100] [--rounds 4] [--episodes 5]
                      [--labels best|mean] [--features observation|state] [--noise-states 200]
                      [--processes 2] [--table ceiling.csv]

Per track it prints the network's score after each round (five deterministic episodes from
start seeds 0-4, mean total reward), the oracle's score on the track (``analysis/data/oracle.csv``
or ``oracle_tuning.csv`` where they have the track, else scored here with the same protocol) and the final score's fraction
of it, and the network's mean squared error on its own data (the fit error: how closely the pupil
matches the oracle where it has labels); then the mean fraction over the tracks with its 95%
bootstrap interval over tracks. ``--labels mean`` labels each state with the mean first action of
the oracle's last elite plans instead of its best plan's (a smoother target). ``--noise-states M``
labels M states of the last round again, ``--noise-labels`` times each by oracles planning from
scratch: the labels' variance per state is the error floor of any function of the state, beside
the pupil's squared error against their mean. ``--features state`` gives the pupil the car's true
state besides the observation (a privileged pupil, not a policy of the task): how well the oracle's
actions can be fitted when nothing is hidden.
``--hidden 256 256`` gives a wider network. One track per process with ``--processes``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from engine.budget import PROCESSES, SEED, check_items, check_work, count
from engine import numerics


def _one(args: tuple):
    track, settings = args
    from pupil.dagger import dagger

    return dagger(track, settings)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tracks", type=SEED, nargs="+", required=True)
    parser.add_argument("--hidden", type=count(1, 4096), nargs="+", default=[100], help="hidden layer sizes (the paper's: 100)")
    parser.add_argument("--rounds", type=count(0, 100), default=4, help="DAgger rounds after the oracle's own episodes")
    parser.add_argument("--episodes", type=count(1, 1000), default=5, help="data episodes per round and track")
    parser.add_argument("--epochs", type=count(1, 100_000), default=300, help="passes over the data per refit")
    parser.add_argument("--labels", choices=["best", "mean"], default="best",
                        help="the oracle's action (best: its best plan's first step) or its last elite mean's")
    parser.add_argument("--features", choices=["observation", "state"], default="observation",
                        help="the pupil's input; state: also the car's true state (a privileged pupil, no policy)")
    parser.add_argument("--noise-states", type=count(0, 100_000), default=0,
                        help="after the last round, label this many of its states again (--noise-labels times each)")
    parser.add_argument("--noise-labels", type=count(1, 1000), default=8, help="labels per state for --noise-states")
    parser.add_argument("--processes", type=PROCESSES, default=1)
    parser.add_argument("--table", type=Path, default=None)
    args = parser.parse_args(argv)
    check_items(parser, "--hidden", args.hidden, 16)
    check_items(parser, "--tracks", args.tracks, 1_000, unique=True)
    widths = [6, *args.hidden, 2]
    check_work(parser, 50_000_000, "weights", network=sum(a * b for a, b in zip(widths, widths[1:])))
    check_work(parser, 1_000_000, "oracle-labelled episodes", tracks=len(args.tracks), rounds=args.rounds + 1,
               episodes=args.episodes)
    from engine.tool_output import check_outputs

    check_outputs(parser, table=args.table)

    numerics.apply(numerics.DEFAULT)
    from analysis.report import read_oracles
    from pupil.dagger import DaggerSettings, mean
    from engine.pool import run_jobs

    try:
        settings = DaggerSettings(rounds=args.rounds, episodes=args.episodes, hidden=tuple(args.hidden),
                                  epochs=args.epochs, label=args.labels, features=args.features,
                                  noise_states=args.noise_states,
                                  noise_labels=args.noise_labels)
    except ValueError as err:
        parser.error(str(err))
    work = [(track, settings) for track in args.tracks]
    results = run_jobs(_one, work, args.processes, numerics.DEFAULT)  # before torch loads; one thread
    oracle = read_oracles()
    missing = [t for t in args.tracks if t not in oracle]
    if missing:
        from racing.oracle import score

        oracle.update({t: r["mean"] for t, r in score(missing, 5).items()})
    rows, fractions = [], []
    for result in results:
        ceiling = oracle[result.track]
        fraction = result.scores[-1] / ceiling
        fractions.append(fraction)
        print(f"track {result.track}: " + ", ".join(f"round {k} {s:.1f}" for k, s in enumerate(result.scores))
              + f"; oracle {ceiling:.1f}; final {fraction:.3f} of the oracle ({result.samples[-1]} labels, "
              f"fit error {result.fit_error[-1]:.4f}, {result.seconds:.0f} s)"
              + ("" if result.label_noise is None else
                 f"; repeated labels: their variance {result.label_noise:.4f}, the pupil's squared error to "
                 f"their mean {result.error_to_mean_label:.4f}"))
        rows += [{"track": result.track, "hidden": " ".join(map(str, settings.hidden)), "label": settings.label,
                  "features": settings.features,
                  "round": k, "score": round(s, 6), "labels": n, "fit_error": round(e, 6), "oracle": round(ceiling, 6),
                  "fraction": round(s / ceiling, 6),
                  "label_noise": "" if result.label_noise is None or k < len(result.scores) - 1 else round(result.label_noise, 6),
                  "error_to_mean_label": "" if result.label_noise is None or k < len(result.scores) - 1
                  else round(result.error_to_mean_label, 6)}
                 for k, (s, n, e) in enumerate(zip(result.scores, result.samples, result.fit_error))]
    from analysis.compare import bootstrap_interval

    low, high = bootstrap_interval(fractions)
    print(f"hidden {list(settings.hidden)}: {mean(fractions):.3f} of the oracle [{low:.3f}, {high:.3f}] over "
          f"{len(fractions)} tracks")
    if args.table is not None:
        from engine.outputs import write_table

        write_table(args.table, rows)
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("imitate", main))
