"""The exact numerics modes (``fma``, the default, and ``portable``) across real CPU models, on
one machine: the same short runs here and under ``qemu-x86_64 -cpu MODEL`` (QEMU's user-mode
emulator, Debian package ``qemu-user``), which runs the same binaries on an emulated CPU whose
identification (vendor, model, instruction sets) MKL, NumPy, glibc, torch and the project's
matrix kernels read to choose their code paths:

    python -m tests.cross_cpu [--cpus Haswell EPYC-Rome] [--cells spg_p_multi/hybrid ...] [--episodes 3]
                              [--numerics fma] [--max-steps 200]

prints one row per run (metrics.csv's hash here and on each emulated CPU) and exits 1 if any
differs. Haswell is an Intel AVX2 CPU, EPYC-Rome an AMD one (QEMU 7.2 emulates no AVX-512, so
"here" is the AVX-512 side when this machine has it). Emulation is slow: about ten minutes for
the defaults. It checks the code paths; QEMU computes the CPU's approximate instructions
(reciprocal square root, reciprocal) exactly where hardware approximates, which is why a
result that uses them (torch's float32 sqrt through MKL) differs under emulation: the project
avoids them (``learners.optim.exact_sqrt``). ``tests/test_emulated_cpu.py`` runs a tiny version
when ``qemu-x86_64`` is installed.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from analysis.report import ALGO_COLUMNS  # the paper's algorithms (the others are off-policy: warm-up overrides)

ROOT = Path(__file__).resolve().parent.parent
CELLS = ["spg_p_multi/hybrid", "ppo_log/recent", "sac/memory"]
SEEDS = "[2067791,5468063]"


def run_here_or_emulated(cpu: str | None, cells: list[str], episodes: int, out: Path,
                         mode: str = "fma", max_steps: int = 200) -> dict[str, str]:
    """metrics.csv hash per run of ``cells`` in numerics ``mode``, on ``cpu`` (None: this machine)."""
    overrides = [[f"algo={c.split('/')[0]}", f"er={c.split('/')[1]}", f"env.options.max_steps={max_steps}"]
                 + (["algo.td.warmup_episodes=1", "algo.td.updates_per_step=0.25"] if c.split("/")[0] not in ALGO_COLUMNS
                    else [f"algo.minibatch_size={max_steps}"] if max_steps < 200 else []) for c in cells]
    code = ("import json, sys\nfrom pathlib import Path\nfrom engine import numerics\n"
            f"numerics.apply('{mode}')\n"
            "from engine.config import RunConfig\nfrom engine.runner import train_population\n"
            "for i, overrides in enumerate(json.loads(sys.argv[1])):\n"
            f"    cfg = RunConfig.compose(*overrides, 'seeds={SEEDS}', 'episodes={episodes}', 'progress=false',\n"
            f"                            'logger=none', 'checkpoint_every=0', 'numerics={mode}')\n"
            "    train_population(cfg, Path(sys.argv[2]) / str(i))\n")
    command = [sys.executable, "-c", code, json.dumps(overrides), str(out)]
    if cpu is not None:
        command = ["qemu-x86_64", "-cpu", cpu, *command]
    env = {**os.environ, "RL_LOGGING_LEVEL": "WARNING", "PYTHONWARNINGS": "ignore"}
    result = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"the runs on {cpu or 'this machine'} failed:\n{result.stderr[-3000:]}")
    hashes = {}
    for i, cell in enumerate(cells):
        for path in sorted((out / str(i)).rglob("metrics.csv")):
            hashes[f"{cell} {path.parent.name}"] = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    return hashes


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cpus", nargs="+", default=["Haswell", "EPYC-Rome"], help="qemu-x86_64 -cpu models")
    parser.add_argument("--cells", nargs="+", default=CELLS)
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--numerics", choices=["fma", "portable"], default="fma")
    parser.add_argument("--max-steps", type=int, default=200, help="steps per episode (shorter: quicker)")
    args = parser.parse_args(argv)
    if shutil.which("qemu-x86_64") is None:
        print("cross_cpu: qemu-x86_64 not found (Debian/Ubuntu: apt install qemu-user)", file=sys.stderr)
        return 2
    import platform

    if platform.machine() not in ("x86_64", "AMD64"):
        print(f"cross_cpu: this machine is {platform.machine()}, not x86-64", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        runs = {"here": run_here_or_emulated(None, args.cells, args.episodes, Path(tmp) / "here", args.numerics,
                                             args.max_steps)}
        for cpu in args.cpus:
            runs[cpu] = run_here_or_emulated(cpu, args.cells, args.episodes, Path(tmp) / cpu, args.numerics,
                                             args.max_steps)
    names = list(runs)
    print("| run | " + " | ".join(names) + " | same |")
    print("|" + "---|" * (len(names) + 2))
    differ = 0
    for run in runs["here"]:
        values = [runs[n].get(run, "missing") for n in names]
        same = len(set(values)) == 1
        differ += not same
        print(f"| {run} | " + " | ".join(values) + f" | {'yes' if same else 'NO'} |")
    print(f"numerics={args.numerics}: {len(runs['here']) - differ} of {len(runs['here'])} runs identical on "
          + ", ".join(["this machine", *args.cpus]))
    return 1 if differ else 0


if __name__ == "__main__":
    raise SystemExit(main())
