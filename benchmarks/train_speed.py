"""Training speed: wall time of paper-length runs, and what each speed-up buys, in one process.

    python -m benchmarks.train_speed [--episodes 201] [--cells spg_p_multi/hybrid ...]

Three tables, each with ratios against a baseline measured here in the same process:
1. hidden-layer tanh: ``learners.solo.tanh`` against ``torch.tanh`` (minibatch sizes);
2. one 200-step episode: the direct collector against ``torchrl.collectors.Collector``;
3. one full run per algorithm (its most expensive replay mode by default), with the time
   spent collecting and training, against the same runs with the TorchRL Collector for one
   configuration (``--baseline``).
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

from engine import numerics  # noqa: E402

# Before torch loads (engine/numerics.py). Imported by a benchmark that loaded torch in its own mode: that one.
if "torch" not in sys.modules:
    numerics.apply(numerics.DEFAULT)

import torch  # noqa: E402

from collectors import make_collector  # noqa: E402
from engine.config import RunConfig  # noqa: E402
from learners.solo import GaussianPolicyNet, make_actor, make_policy, make_sampler, tanh  # noqa: E402
from engine.runner import train  # noqa: E402
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
    table("Hidden-layer tanh (microseconds per call)", ["input", "torch.tanh", "models.tanh", "speed-up"], rows)


def collector_table(episodes: int) -> None:
    times = {}
    for backend in ("torchrl", "direct"):
        torch.manual_seed(0)
        net = GaussianPolicyNet(6, 2, [100])
        env = RacingTorchEnv(1, track_seeds=[2067791])
        env.set_seed(0)
        collector = make_collector(backend, env, policy=make_policy(make_actor(net)), sample=make_sampler(net),
                                   steps=200, episodes=episodes + 1)
        batches = iter(collector)
        next(batches)  # warm-up
        start = time.perf_counter()
        for _ in range(episodes):
            next(batches)
        times[backend] = (time.perf_counter() - start) / episodes
        collector.shutdown()
    base = times["torchrl"]
    rows = [[name, f"{t * 1e3:.1f}", f"{base / t:.2f}x"] for name, t in
            (("torchrl.collectors.Collector (baseline)", base), ("collectors.DirectCollector", times["direct"]))]
    table("One 200-step episode, one car (milliseconds)", ["collector", "ms / episode", "speed-up"], rows)


def run(cell: str, episodes: int, *overrides: str) -> dict:
    algo, er = cell.split("/")
    cfg = RunConfig.compose(f"algo={algo}", f"er={er}", f"episodes={episodes}", "progress=false", "logger=none",
                            *overrides)
    with tempfile.TemporaryDirectory() as out:
        return train(cfg, Path(out))


def run_table(cells: list[str], episodes: int, baseline: str | None) -> None:
    rows = []
    base = None
    if baseline:
        s = run(baseline, episodes, "env.collector=torchrl")
        base = s["wall_time_s"]
        rows.append([f"{baseline} (TorchRL Collector, baseline)", f"{s['wall_time_s']:.1f}",
                     f"{s['time/rollout_s']:.1f}", f"{s['time/train_s']:.1f}", "1.00x", f"{s['final_mean']:.1f}"])
    for cell in cells:
        s = run(cell, episodes)
        ratio = f"{base / s['wall_time_s']:.2f}x" if base and cell == baseline else ""
        rows.append([cell, f"{s['wall_time_s']:.1f}", f"{s['time/rollout_s']:.1f}", f"{s['time/train_s']:.1f}",
                     ratio, f"{s['final_mean']:.1f}"])
    table(f"Full runs, {episodes} episodes, track 2067791, one thread (seconds)",
          ["algo/er", "wall", "collecting", "training", "speed-up", "final_mean"], rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=201, help="episodes per full run (paper: 201)")
    parser.add_argument("--cells", nargs="*", default=DEFAULT_CELLS, help="algo/er pairs to time")
    parser.add_argument("--baseline", default="spg_p_multi/hybrid",
                        help="algo/er also run with the TorchRL Collector ('' to skip)")
    parser.add_argument("--repeats", type=int, default=20, help="repeats of the micro-benchmarks")
    args = parser.parse_args()
    torch.set_num_threads(1)
    tanh_table(args.repeats)
    collector_table(max(2, args.repeats // 2))
    run_table(args.cells, args.episodes, args.baseline or None)


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("benchmarks.train_speed", main))
