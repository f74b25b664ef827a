"""Writes ``tests/data/rliable_reference.json``: rliable's own numbers on fixed data, which
``tests/test_aggregate.py`` holds ``analysis.aggregate`` to (as the simulator is held to the reference
simulator's vectors).

rliable does not import beside this project's pins (its ``arch`` dependency fails against pandas 3,
which tensordict prefers), so this runs in an environment of its own:

    python3 -m venv /tmp/rliable-env
    /tmp/rliable-env/bin/pip install rliable==1.2.0 "pandas<3"
    /tmp/rliable-env/bin/python tests/rliable_reference.py

It needs rliable and NumPy only (not this project). Each task's runs are sorted first, as
``analysis.aggregate`` sorts them; rliable draws its resamples from NumPy's global generator, seeded
here before each estimate.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parent / "data" / "rliable_reference.json"
SEED = 7
REPS = 50_000
PROFILE_REPS = 2_000


def data() -> dict[str, np.ndarray]:
    """Matrices [runs, tasks] as the report and the leaderboard make them (one task of many runs; a few runs
    on many tracks), with ties, sorted within each task."""
    rng = np.random.RandomState(2021)
    cells = {
        "five runs, one task": rng.normal(130, 12, (5, 1)),
        "three runs, ten tasks": rng.normal(0.85, 0.05, (3, 10)),
        "twenty-five runs, one task": np.round(rng.normal(0.8, 0.1, (25, 1)), 2),  # ties
        "other five runs, one task": rng.normal(120, 15, (5, 1)),
        "other three runs, ten tasks": rng.normal(0.8, 0.08, (3, 10)),
        "two runs, ten tasks": rng.normal(0.8, 0.08, (2, 10)),
    }
    return {name: np.sort(m, axis=0) for name, m in cells.items()}


def main() -> int:
    from rliable import library, metrics

    cells = data()
    estimators = {"IQM": metrics.aggregate_iqm, "mean": metrics.aggregate_mean,
                  "median": metrics.aggregate_median, "optimality gap": metrics.aggregate_optimality_gap}
    out = {"seed": SEED, "reps": REPS, "profile_reps": PROFILE_REPS,
           "data": {name: m.tolist() for name, m in cells.items()}, "intervals": {}, "improvement": {},
           "profiles": {}}
    for name, scores in cells.items():
        for estimator, func in estimators.items():
            np.random.seed(SEED)
            point, ci = library.get_interval_estimates({name: scores}, lambda x, f=func: np.array([f(x)]), reps=REPS)
            out["intervals"][f"{estimator} | {name}"] = [float(point[name][0]), float(ci[name][0, 0]),
                                                          float(ci[name][1, 0])]
    for x, y in (("five runs, one task", "other five runs, one task"),
                 ("three runs, ten tasks", "other three runs, ten tasks"),
                 ("three runs, ten tasks", "two runs, ten tasks")):
        np.random.seed(SEED)
        key = f"{x} | {y}"
        point, ci = library.get_interval_estimates(
            {key: [cells[x], cells[y]]}, lambda a, b: np.array([metrics.probability_of_improvement(a, b)]), reps=REPS)
        out["improvement"][key] = [float(point[key][0]), float(ci[key][0, 0]), float(ci[key][1, 0])]
    taus = np.linspace(0.5, 1.1, 13)
    for name in ("three runs, ten tasks", "twenty-five runs, one task"):
        np.random.seed(SEED)
        profile, ci = library.create_performance_profile({name: cells[name]}, taus, reps=PROFILE_REPS)
        out["profiles"][name] = {"taus": taus.tolist(), "profile": profile[name].tolist(),
                                 "low": ci[name][0].tolist(), "high": ci[name][1].tolist()}
    import rliable

    out["rliable"] = getattr(rliable, "__version__", "unknown")
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
