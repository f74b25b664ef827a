"""How the oracle's score grows with its planning budget: is the ceiling near converged?

    python -m speed.oracle_convergence [--tracks ...] [--episodes 2]

Runs ``racing.oracle.Oracle`` (cross-entropy MPC on the true simulator) with a ladder of
settings, one planning dimension varied at a time around a base (``OracleSettings()`` unless
``--candidates/--horizon/--iterations``), on the tuning tracks 1001-1003 by default (neither
the paper's nor the wide grid's), and prints the mean total reward over tracks and episodes,
its difference from the base's (paired by track and episode), and the time per episode. Start states are those of ``evaluate.py`` (``reset(seed=k)``, k = 0, 1, ...). A ceiling
is near converged where larger budgets no longer raise the score beyond the episode-to-episode
noise.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time

import numpy as np

import racing
from engine.budget import EPISODES, SEED, count
from racing.oracle import Oracle, OracleSettings, drive



def ladder(base: OracleSettings) -> list[dict]:
    """One planning dimension at a time, below and above ``base``."""
    c, h, i = base.candidates, base.horizon, base.iterations
    return [dict(candidates=max(1, c // 4)), dict(candidates=max(1, c // 2)), dict(candidates=c * 4),
            dict(horizon=max(1, h // 2)), dict(horizon=max(1, h * 3 // 4)), dict(horizon=h * 3 // 2),
            dict(horizon=h * 2), dict(iterations=1), dict(iterations=i * 2)]


def scores(settings: OracleSettings, tracks: list[int], episodes: int) -> tuple[list[float], float]:
    totals, start = [], time.perf_counter()
    for track in tracks:
        env = racing.RacingEnv(track_seed=track)
        oracle = Oracle(settings, seed=0)
        totals += [drive(env, oracle, seed) for seed in range(episodes)]
    return totals, (time.perf_counter() - start) / len(totals)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracks", type=SEED, nargs="+", default=[1001, 1002, 1003])
    parser.add_argument("--episodes", type=EPISODES, default=2)
    parser.add_argument("--candidates", type=count(1, 100_000), default=None, help="the base setting (default: OracleSettings())")
    parser.add_argument("--horizon", type=count(1, 1000), default=None)
    parser.add_argument("--iterations", type=count(1, 1000), default=None)
    parser.add_argument("--ladder", type=count(1, 1000), default=None, help="run only the first N rungs (tests)")
    args = parser.parse_args(argv)
    base = dataclasses.replace(OracleSettings(), **{k: getattr(args, k) for k in ("candidates", "horizon", "iterations")
                                                     if getattr(args, k) is not None})
    reference, reference_time = scores(base, args.tracks, args.episodes)
    print(f"oracle on tracks {args.tracks}, {args.episodes} episodes each; base {base}\n")
    print("| setting | mean total reward | vs base (paired, ± SE) | s per episode |")
    print("|---|---:|---:|---:|")
    rows = [("base", reference, reference_time)]
    for change in ladder(base)[:args.ladder]:
        settings = dataclasses.replace(base, **change)
        rows.append((", ".join(f"{k}={v}" for k, v in change.items()), *scores(settings, args.tracks, args.episodes)))
    for name, totals, seconds in rows:
        diff = np.array(totals) - np.array(reference)
        se = diff.std(ddof=1) / math.sqrt(len(diff)) if len(diff) > 1 else float("nan")
        vs = "(reference)" if name == "base" else f"{diff.mean():+.2f} ± {se:.2f}"
        print(f"| {name} | {np.mean(totals):.2f} | {vs} | {seconds:.2f} |")


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("speed.oracle_convergence", main))
