"""How trained policies drive, beside the oracle on the same tracks and start states: where the score goes.

    python -m analysis.driving RUN_DIR... [--episodes 5] [--seed 0] [--no-oracle] [--table driving.csv]
                                         [--full-throttle-above T]

For each run folder (or every run under a sweep's folder) its final deterministic policy drives
``--episodes`` episodes on its own track from the start states of ``--seed``, ``--seed + 1``, ...
(``evaluate.py``'s protocol, in the numerics the runs trained in), and the oracle (``racing.oracle``,
a planner that sees the true state) drives the same episodes. Per driver and track it prints the mean
total reward, the steps that left the track per episode, the mean speed, and how the throttle was
used: the share of steps at full throttle (>= 0.99), braking (< 0), and the mean throttle. The reward
is the speed, so a policy that never leaves the track loses to the oracle only by driving slower.

``--full-throttle-above T`` is a diagnostic, not a policy: every throttle of the trained policies at or
above T is replaced by 1 (full throttle) before the car takes it (the rows are named ``... (throttle >= T
-> 1)``). It asks whether the policies lose speed where a squashed or penalised output stops short of
full throttle, or where they would crash at full speed. Nothing is trained or chosen with it.
"""

from __future__ import annotations

import argparse
import math
import sys
from engine.budget import SEED, count, real
from pathlib import Path

COLUMNS = ("driver", "track", "episodes", "mean_reward", "crashes_per_episode", "mean_speed", "full_throttle",
           "braking", "mean_throttle")


def drive(act, env, seed: int, reset) -> dict:
    """One episode of ``act(env, observation)``: its total reward, crashes, speeds and throttles."""
    import numpy as np

    from engine.evaluation import drive_episode

    speeds, throttles = [], []

    def recorded(env, observation):
        action = np.asarray(act(env, observation), dtype=np.float64)
        speeds.append(float(env.unwrapped.sim.speed[0]))
        throttles.append(float(np.clip(action[0], -1.0, 1.0)))
        return action

    total = drive_episode(recorded, env, seed, reset=reset)
    return {"reward": total, "crashes": int(env.unwrapped.sim.crashes[0]), "speeds": speeds, "throttles": throttles}


def summarise(driver: str, track, episodes: list[dict]) -> dict:
    speeds = [v for e in episodes for v in e["speeds"]]
    throttles = [t for e in episodes for t in e["throttles"]]
    return {"driver": driver, "track": track, "episodes": len(episodes),
            "mean_reward": round(math.fsum(e["reward"] for e in episodes) / len(episodes), 4),
            "crashes_per_episode": round(sum(e["crashes"] for e in episodes) / len(episodes), 3),
            "mean_speed": round(math.fsum(speeds) / len(speeds), 3),
            "full_throttle": round(sum(t >= 0.99 for t in throttles) / len(throttles), 3),
            "braking": round(sum(t < 0 for t in throttles) / len(throttles), 3),
            "mean_throttle": round(math.fsum(throttles) / len(throttles), 3)}


def driving_rows(runs: list[Path], episodes: int, seed: int = 0, oracle: bool = True,
                 full_throttle_above: float | None = None) -> list[dict]:
    """A row per run (its policy on its own track; with ``full_throttle_above``, a second row with its
    throttles at or above it made full), and per track the oracle's on the same episodes."""
    from engine.evaluation import load_policy, make_env, own_track
    from racing.oracle import Oracle

    rows, oracle_done = [], set()
    for run in runs:
        policy, settings = load_policy(run)
        track = own_track(settings)
        env = make_env(settings, track)
        rows.append(summarise(str(run), track, [drive(lambda e, o: policy(o), env, seed + k, policy.reset)
                                                for k in range(episodes)]))
        if full_throttle_above is not None:
            def boosted(e, o):
                action = policy(o).copy()
                if action[0] >= full_throttle_above:
                    action[0] = 1.0
                return action

            rows.append(summarise(f"{run} (throttle >= {full_throttle_above:g} -> 1)", track,
                                  [drive(boosted, env, seed + k, policy.reset) for k in range(episodes)]))
        key = (str(track), repr({k: v for k, v in settings["env"].items() if k != "memory"}))
        if oracle and key not in oracle_done:  # once per track and environment (a policy's memory is not the oracle's)
            oracle_done.add(key)
            planner = Oracle()
            rows.append(summarise("oracle", track, [drive(lambda e, o: planner.act(e.unwrapped.sim, 0), env, seed + k,
                                                          planner.reset) for k in range(episodes)]))
        env.close()
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", type=Path, nargs="+", help="run folders, or sweep folders holding them")
    parser.add_argument("--episodes", type=count(1, 1000), default=5, help="episodes per driver and track (default 5)")
    parser.add_argument("--seed", type=SEED, default=0, help="the first start state's seed (default 0)")
    parser.add_argument("--no-oracle", action="store_true", help="leave the oracle out (it plans: ~3 s an episode)")
    parser.add_argument("--table", type=Path, default=None, help="also write the rows as CSV")
    parser.add_argument("--full-throttle-above", type=real(-1, 1), default=None, metavar="T",
                        help="also drive each policy with its throttles >= T made full (a diagnostic)")
    args = parser.parse_args(argv)
    from engine.processes import check_start_seeds
    from engine.tool_output import check_outputs

    check_outputs(parser, reads=args.paths, table=args.table)

    check_start_seeds(parser, args.seed, args.episodes)
    if args.table is not None and args.table.is_dir():  # refused before the driving, not after it
        parser.error(f"--table {args.table} is a folder; give a file name (e.g. {args.table / 'driving.csv'})")
    from engine import numerics
    from engine.outputs import RunFolderError
    from engine.rundir import runs_numerics
    from engine.runset import read_runs

    try:
        runs = read_runs(args.paths, say="driving").runs  # each run once
        numerics.apply(runs_numerics(runs))  # before torch loads: the runs' own numerics
        rows = driving_rows(runs, args.episodes, args.seed, oracle=not args.no_oracle,
                            full_throttle_above=args.full_throttle_above)
    except (RunFolderError, numerics.NumericsError) as err:
        print(f"driving: {err}", file=sys.stderr)
        return 2
    print("| " + " | ".join(COLUMNS) + " |")
    print("|" + "---|" * len(COLUMNS))
    for row in rows:
        print("| " + " | ".join(str(row[c]) for c in COLUMNS) + " |")
    if args.table is not None:
        from engine.outputs import write_table

        write_table(args.table, rows)  # its folders made as needed, the file replaced whole
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("analysis.driving", main))
