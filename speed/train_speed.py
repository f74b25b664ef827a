"""Training speed: wall time of paper-length runs, and what each speed-up buys, in one process.

    python -m speed.train_speed [--episodes 201] [--cells spg_p_multi/hybrid ...] [--pairs 2]

Three tables, each with ratios against a baseline measured here in the same process:
1. hidden-layer tanh: ``learners.solo.tanh`` against ``torch.tanh`` (minibatch sizes);
2. one car's 200-step episodes: the TorchRL ``Collector`` as a run uses it (the default,
   ``env.collector=torchrl``) against the direct loop, and with each of its lean pieces put
   back to TorchRL's default (what each saves);
3. whole runs per algorithm (its most expensive replay mode by default) with each collector,
   alternated: the Collector's whole-run cost against the direct loop's, and the same
   ``metrics.csv`` from both.
Absolute numbers depend on the machine; compare ratios across machines. One thread, as the
training runs use.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")

from engine.budget import EPISODES, count
from engine import numerics  # noqa: E402

# Before torch loads (engine/numerics.py). Imported by a benchmark that loaded torch in its own mode: that one.
if "torch" not in sys.modules:
    numerics.apply(numerics.DEFAULT)

import torch  # noqa: E402

from collectors import ActingPolicy, make_collector  # noqa: E402
from engine.config import RunConfig  # noqa: E402
from learners.solo import GaussianPolicyNet, make_sampler, tanh  # noqa: E402
from engine.runner import train  # noqa: E402
from door import files  # noqa: E402
from racing.torchrl_env import RacingTorchEnv  # noqa: E402

DEFAULT_CELLS = ["ppo/recent", "ppo_log/memory", "spg/hybrid", "spg_multi/hybrid", "spg_p/hybrid",
                 "spg_p_multi/hybrid"]


def best_of(fn, repeats: int) -> float:
    """Smallest wall time of ``repeats`` calls (the machine's noise only ever adds time)."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def positive_int(text: str, high: int | None = None) -> int:
    """An argparse type: a whole number of at least 1 (and at most ``high``: ``at_most(high)``),
    refused in one line otherwise."""
    import argparse

    expected = f"a whole number from 1 to {high:,}" if high else "a whole number >= 1"
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
    if value < 1 or (high is not None and value > high):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {value}")
    return value


def at_most(high: int):
    """``positive_int`` with a ceiling, for argparse's ``type=``."""
    def parse(text: str) -> int:
        return positive_int(text, high)
    return parse


def table(title: str, header: list[str], rows: list[list]) -> None:
    print(f"\n{title}\n")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in rows:
        print("| " + " | ".join(str(x) for x in row) + " |")


def tanh_table(repeats: int) -> None:
    rows = []
    for shape in [(200, 100), (1400, 100)]:
        x = torch.randn(shape)
        base = best_of(lambda: [torch.tanh(x) for _ in range(20)], repeats)
        ours = best_of(lambda: [tanh(x) for _ in range(20)], repeats)
        rows.append([f"{shape[0]} x {shape[1]}", f"{base / 20 * 1e6:.1f}", f"{ours / 20 * 1e6:.1f}",
                     f"{base / ours:.2f}x"])
    table("Hidden-layer tanh (microseconds per call)", ["input", "torch.tanh", "learners.solo.tanh", "speed-up"], rows)


def collector_table(episodes: int) -> None:
    """One car's 200-step episodes through each collector, and through the Collector with each of
    its lean pieces put back to TorchRL's default, alternated: what each piece saves per step."""
    from tensordict.nn import TensorDictModule
    from torchrl.collectors import Collector
    from torchrl.envs import EnvBase

    class TorchRLStep(RacingTorchEnv):  # EnvBase's own step_and_maybe_reset (checks, done completion, step_mdp)
        _step_and_maybe_reset = EnvBase._step_and_maybe_reset

    def collector(variant: str, env, sample):
        if variant == "direct":
            return make_collector("direct", env, sample=sample, steps=200, episodes=episodes + 1)
        if variant == "torchrl":
            return make_collector("torchrl", env, sample=sample, steps=200, episodes=episodes + 1)
        policy = TensorDictModule(sample, in_keys=["observation"], out_keys=["action"]) if variant == "module" \
            else ActingPolicy(sample)
        return Collector(env, policy, frames_per_batch=200, total_frames=200 * (episodes + 1), device=env.device,
                         trust_policy=True, auto_register_policy_transforms=False,
                         track_traj_ids=variant == "traj_ids")

    names = {"direct": "collectors.DirectCollector (baseline)", "torchrl": "Collector, as a run uses it",
             "traj_ids": "  with track_traj_ids=True", "module": "  with a TensorDictModule policy",
             "envbase": "  with EnvBase's step_and_maybe_reset"}
    times: dict[str, list[float]] = {name: [] for name in names}
    for repeat in range(3):
        for variant in (names if repeat % 2 == 0 else reversed(list(names))):
            torch.manual_seed(0)
            net = GaussianPolicyNet(6, 2, [100])
            env = (TorchRLStep if variant == "envbase" else RacingTorchEnv)(1, track_seeds=[2067791])
            env.set_seed(0)
            batches = iter(collector(variant, env, make_sampler(net)))
            next(batches)  # warm-up
            start = time.perf_counter()
            for _ in range(episodes):
                next(batches)
            times[variant].append((time.perf_counter() - start) / episodes / 200)
    base = min(times["direct"])
    rows = [[label, f"{min(times[v]) * 1e6:.0f}", f"{(min(times[v]) - base) * 1e6:+.0f}", f"{min(times[v]) / base:.2f}x"]
            for v, label in names.items()]
    table("One car, 200-step episodes (microseconds per step, best of 3 alternated)",
          ["collector", "us / step", "against the baseline", "cost"], rows)


def run(cell: str, episodes: int, collector: str) -> dict:
    algo, er = cell.split("/")
    cfg = RunConfig.compose(f"algo={algo}", f"er={er}", f"episodes={episodes}", "progress=false", "logger=none",
                            f"env.collector={collector}")
    with tempfile.TemporaryDirectory() as out:
        summary = train(cfg, Path(out))
        summary["metrics_bytes"] = files.read(Path(out) / "metrics.csv", 1 << 30, "metrics.csv")
        return summary


def run_table(cells: list[str], episodes: int, pairs: int) -> None:
    """Whole runs of each cell with each collector, alternated (direct, torchrl, torchrl, direct, ...):
    the Collector's whole-run cost against the direct loop's, and whether the runs are the same."""
    rows, totals = [], {"direct": 0.0, "torchrl": 0.0}
    for cell in cells:
        walls: dict[str, list[float]] = {"direct": [], "torchrl": []}
        metrics = set()
        for k in range(pairs):
            for collector in (("direct", "torchrl") if k % 2 == 0 else ("torchrl", "direct")):
                s = run(cell, episodes, collector)
                walls[collector].append(s["wall_time_s"])
                metrics.add(s["metrics_bytes"])
        best = {c: min(w) for c, w in walls.items()}
        for c in totals:
            totals[c] += best[c]
        rows.append([cell, f"{best['direct']:.1f}", f"{best['torchrl']:.1f}", f"{best['torchrl'] / best['direct']:.3f}",
                     "yes" if len(metrics) == 1 else "NO"])
    rows.append(["all cells", f"{totals['direct']:.1f}", f"{totals['torchrl']:.1f}",
                 f"{totals['torchrl'] / totals['direct']:.3f}", ""])
    table(f"Whole runs, {episodes} episodes, track 2067791, one thread (seconds, best of {pairs} alternated)",
          ["algo/er", "direct loop", "TorchRL Collector", "Collector / direct", "same metrics.csv"], rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=EPISODES, default=201, help="episodes per full run (paper: 201)")
    parser.add_argument("--cells", nargs="*", default=DEFAULT_CELLS, help="algo/er pairs to time")
    parser.add_argument("--pairs", type=at_most(100), default=2, help="alternated pairs of whole runs per cell")
    parser.add_argument("--repeats", type=count(1, 1000), default=20, help="repeats of the micro-benchmarks")
    args = parser.parse_args()
    tanh_table(args.repeats)
    collector_table(max(2, args.repeats // 2))
    run_table(args.cells, args.episodes, args.pairs)


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("speed.train_speed", main))
