"""The RAM estimate (``engine.limits.estimate``) against what runs actually take: the table behind its constants.

    python -m speed.memory_estimate [--grid default|quick] [--keep-going]

Each row is one ``train.py`` run in a fresh process (one episode, progress and logging off, its own
temporary folder); its peak resident memory is the process's ``ru_maxrss`` as the kernel reports it at
exit. The table gives the estimate, the measured peak and their ratio (estimate / peak), each meant to
lie within 1.5 times either way. One configuration's peak is not one number: a population of nine
Monte-Carlo members over a 20,000-step episode peaked between 1.07 GB and 1.76 GB over six processes (the allocator's doing, by how the steps' small tensors fall among freed larger ones; not
itemised), so a row can move between runs of this script. The default grid spans the sizes that
move the estimate: episode length (200 to 200,000 steps), population size (1 to 9), both collectors,
both families; ``quick`` is its cheapest rows (tests/test_limits.py). Not in it: the replay memory,
which the estimate counts at its full size (allocated whole, its pages resident as it fills: a run's
peak once full, which a one-episode run does not reach) with its checkpoint copies.
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LOW, HIGH = 1 / 1.5, 1.5  # the estimate / peak ratios a row should fall within
QUICK = (
    "algo=ppo er=recent",
    "algo=ppo er=recent env.options.max_steps=20000 seeds=[1,2,3]",
    "algo=sac er=memory algo.td.warmup_episodes=0 env.options.max_steps=20000",
)
GRID = QUICK + (
    "algo=ppo er=recent env.options.max_steps=60000",
    "algo=ppo er=recent env.options.max_steps=60000 env.collector=direct",
    "algo=ppo er=recent env.options.max_steps=20000 seeds=[1,2,3,4,5,6,7,8,9]",
    "algo=spg_p_multi er=memory env.options.max_steps=60000",
    "algo=spg er=recent env.options.max_steps=20000 seeds=[1,2,3] env.collector=direct",
    "algo=sac er=memory algo.td.warmup_episodes=0 env.options.max_steps=60000",
    "algo=sac er=memory algo.td.warmup_episodes=0 env.options.max_steps=60000 env.collector=direct",
    "algo=sac er=memory algo.td.warmup_episodes=0 env.options.max_steps=20000 seeds=[1,2,3,4,5,6,7,8,9]",
    "algo=sac er=memory algo.td.warmup_episodes=0 env.options.max_steps=200000",
)


def peak_bytes(overrides: list[str], folder: str) -> int:
    """The peak resident memory of ``train.py overrides`` run to its end in a fresh process."""
    command = [sys.executable, str(ROOT / "train.py"), *overrides, "episodes=1", "progress=false", "logger=none",
               f"hydra.run.dir={folder}/run"]
    process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, stderr = process.communicate()
    if process.returncode:
        raise SystemExit(f"train.py {' '.join(overrides)} failed: {stderr.decode(errors='replace').strip()[-400:]}")
    # The largest peak among this process's reaped children (KiB on Linux): each row is measured from a process
    # of its own (``--one``), so that one child is all there is.
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024


def measure_one(overrides: str) -> tuple[int, int, dict[str, int]]:
    """(estimate, measured peak, estimate by part) of one row, measured in a child of a fresh process."""
    result = subprocess.run([sys.executable, "-m", "speed.memory_estimate", "--one", overrides], cwd=ROOT,
                            capture_output=True, text=True)
    if result.returncode:
        raise SystemExit(result.stderr.strip().splitlines()[-1] if result.stderr.strip() else "a row failed")
    estimate, peak, *parts = result.stdout.split()
    return int(estimate), int(peak), dict(part.split("=") for part in parts)


def _one(overrides: str) -> None:
    from engine.config import RunConfig
    from engine.limits import estimate

    try:
        parts = estimate(RunConfig.compose(*overrides.split(), "episodes=1"))
    except Exception as err:  # noqa: BLE001 (Hydra's composition errors, the configuration's refusals)
        raise SystemExit(f"memory_estimate: {overrides}: {str(err).splitlines()[0]}") from None
    with tempfile.TemporaryDirectory() as folder:
        peak = peak_bytes(overrides.split(), folder)
    print(sum(parts.values()), peak, *(f"{name.replace(' ', '_')}={size}" for name, size in parts.items()))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--grid", choices=("default", "quick"), default="default")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        _one(args.one)
        return 0
    rows = GRID if args.grid == "default" else QUICK
    print(f"| run (one episode) | estimate | measured peak | estimate / peak |\n|---|---:|---:|---:|")
    outside = 0
    for overrides in rows:
        estimate, peak, _ = measure_one(overrides)
        ratio = estimate / peak
        outside += not LOW <= ratio <= HIGH
        print(f"| {overrides} | {estimate / 2**20:,.0f} MB | {peak / 2**20:,.0f} MB | {ratio:.2f} |", flush=True)
    print(f"\n{len(rows) - outside} of {len(rows)} rows within [{LOW:.2f}, {HIGH:.2f}]")
    return 1 if outside else 0


if __name__ == "__main__":
    from engine.processes import run_tool

    sys.exit(run_tool("speed.memory_estimate", main))
