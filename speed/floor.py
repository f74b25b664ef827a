"""Each learner's gradient step beside its floor: the time its matrix products alone take.

    python -m speed.floor [--sizes 1 5 25] [--steps 30] [--learners sac td3 ...] [--module]

For each learner (``LEARNERS``: its recipe's overrides) and population size R, one short
population run on one thread with the default numerics (``fma``: every product of the networks
goes through ``learners.kernels``). The last episode's update phase is timed as the learner pays
it (minibatches, losses, backward passes, Adam, priorities, target updates) and every product it
makes is recorded (shapes and strides, and the bias gradients' column sums). Those products are
then replayed alone, on buffers of the same layout, outside any network: that is the floor, the
time the step could not go below without faster products. The table gives, per learner and R,
milliseconds per gradient step (the population's; the paper's learners per update phase, of
``value_epochs + policy_epochs`` steps), the floor, their ratio, and the products' count. The
learners with a fused step (``learners.td.learner.FUSED``: SAC, DroQ, BRO, TQC, CrossQ, TD3, the same bits as
their TorchRL loss modules; ``learners.monte_carlo.learner.FUSED``: SPG's and PPO's phases, the same bits as
``SPGLoss`` and ``LogClipPPOLoss``) take it; ``--module`` adds a row through the loss module for each learner
whose run took a fused step, the step before it was fused.

A ratio of 1.0 would mean nothing but products; what lies above it is element-wise work,
autograd's and Python's per-call work and the minibatches. Absolute times depend on the machine
and the hour; the ratio is measured in one process, step and floor minutes apart.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections import defaultdict
from pathlib import Path

os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")

from engine import numerics  # noqa: E402

numerics.apply(numerics.DEFAULT)

from speed.population_speed import member_seeds  # noqa: E402
from speed.train_speed import at_most, table  # noqa: E402

# name: (overrides, off-policy). The off-policy learners with the settings of their results; the
# paper's learners as the paper grid's best cells and PPO.
LEARNERS = {
    "sac": (["algo=sac", "er=memory"], True),
    "td3": (["algo=td3", "er=memory"], True),
    "tqc": (["algo=tqc", "er=memory"], True),
    "crossq": (["algo=crossq", "er=memory"], True),
    "redq": (["algo=redq", "er=prioritised"], True),
    "bro": (["algo=bro", "er=prioritised"], True),
    "droq": (["algo=droq", "er=prioritised"], True),
    "naf": (["algo=naf", "er=memory"], True),
    "trust_pcl": (["algo=trust_pcl", "er=memory"], True),
    "spg_p": (["algo=spg_p", "er=hybrid"], False),
    "spg_p_multi": (["algo=spg_p_multi", "er=memory"], False),
    "ppo": (["algo=ppo", "er=recent"], False),
}


class Recorder:
    """The products (``ops._product``) and column sums (``ops.colsum``) made while ``on``, and the
    time and gradient steps of the update phases, per episode."""

    def __init__(self):
        self.on = False
        self.calls: dict[int, list] = defaultdict(list)
        self.seconds: dict[int, float] = defaultdict(float)
        self.steps: dict[int, int] = defaultdict(int)
        self.episode = 0
        self.fused = False  # whether the phases took a fused step (``TDPhaseRunner.fused``, ``PhaseRunner.fused``)

    def install(self):
        """Wrap the kernels' entry points and both families' update phases; returns the undo."""
        from learners.kernels import ops
        from learners.monte_carlo.learner import PhaseRunner
        from learners.td.learner import TDPhaseRunner

        product, colsum = ops._product, ops.colsum
        td_run, mc_run = TDPhaseRunner.run, PhaseRunner.run
        recorder = self

        def recorded_product(a, sa, b, sb, n, bias, code):
            if recorder.on:
                recorder.calls[recorder.episode].append(
                    ("gemm", code, tuple(a.shape), tuple(sa), tuple(sb), n,
                     None if bias is None else tuple(bias.stride())))
            return product(a, sa, b, sb, n, bias, code)

        def recorded_colsum(x):
            if recorder.on:
                recorder.calls[recorder.episode].append(("colsum", tuple(x.shape), tuple(x.stride())))
            return colsum(x)

        def timed(run, steps_of):
            def wrapper(phases, data, minibatch_size, totals, episode=0):
                for earlier in [e for e in recorder.calls if e < episode]:  # only the last episode is replayed
                    del recorder.calls[earlier]
                recorder.episode, recorder.on = episode, True
                recorder.fused = bool(getattr(phases, "fused", False))
                recorder.steps[episode] += steps_of(phases, episode)
                start = time.perf_counter()
                try:
                    return run(phases, data, minibatch_size, totals, episode)
                finally:
                    recorder.seconds[episode] += time.perf_counter() - start
                    recorder.on = False
            return wrapper

        ops._product, ops.colsum = recorded_product, recorded_colsum
        TDPhaseRunner.run = timed(td_run, lambda p, e: p.updates(e)[1])
        PhaseRunner.run = timed(mc_run, lambda p, e: p.value_epochs + p.policy_epochs)

        def undo():
            ops._product, ops.colsum = product, colsum
            TDPhaseRunner.run, PhaseRunner.run = td_run, mc_run
        return undo


def _extent(shape: tuple, strides: tuple) -> int:
    return 1 + sum((size - 1) * stride for size, stride in zip(shape, strides))


REPLAY_BYTES = 512 * 2**20  # the random buffers replayed at once (a chunk of the calls): bounds the memory


def replay(calls: list, repeats: int = 3, budget: int = REPLAY_BYTES) -> float:
    """Seconds the recorded products take alone, on random buffers of their layouts (each call its
    own, as each product of a step reads fresh activations), the outputs written to buffers made
    once: the calls in chunks whose buffers fit ``budget`` bytes (a population of 25 records
    gigabytes of operands over a few hundred steps), each chunk the best of ``repeats``, summed."""
    import torch

    from learners.kernels import _lib
    from learners.kernels.ops import _gemm

    gemm, colsum = _gemm(), _lib().racing_colsum
    total, prepared, held = 0.0, [], 0
    for index, call in enumerate(calls):
        if call[0] == "gemm":
            _, code, (R, M, K), sa, sb, n, bias_stride = call
            a = torch.randn(_extent((R, M, K), sa))
            b = torch.randn(_extent((R, K, n), sb))
            out = torch.empty(R * M * n)
            bias = None if bias_stride is None else torch.randn(_extent((R, n), bias_stride))
            args = (code, R, M, n, K, a.data_ptr(), *sa, b.data_ptr(), *sb, out.data_ptr(), M * n, n, 1,
                    None if bias is None else bias.data_ptr(), *(bias_stride or (0, 0)))
            buffers = (a, b, out, bias)
            prepared.append((gemm, args, buffers))
        else:
            _, (R, M, N), s = call
            x, out = torch.randn(_extent((R, M, N), s)), torch.empty(R * N)
            buffers = (x, out)
            prepared.append((colsum, (R, M, N, x.data_ptr(), *s, out.data_ptr(), N), buffers))
        held += sum(t.numel() * t.element_size() for t in buffers if t is not None)
        if held >= budget or index == len(calls) - 1:
            best = float("inf")
            for _ in range(repeats):
                start = time.perf_counter()
                for fn, args, _keep in prepared:
                    fn(*args)
                best = min(best, time.perf_counter() - start)
            total, prepared, held = total + best, [], 0
    return total


def measure(recipe: list[str], off_policy: bool, members: int, steps: int, fused: bool = True) -> dict:
    """The last episode's update phases of a short run: seconds, gradient steps, and the seconds
    their products take replayed alone."""
    from engine.config import RunConfig
    from engine.runner import train_population

    seeds = ",".join(map(str, member_seeds(members)))
    extra = ["episodes=3", "final_window=1", "algo.td.warmup_episodes=1",
             f"algo.td.updates_per_step={steps / 200}"] if off_policy else ["episodes=3", "final_window=1"]
    cfg = RunConfig.compose(*recipe, *extra, "progress=false", "logger=none", "checkpoint_every=0",
                            f"seeds=[{seeds}]")
    from learners.monte_carlo import learner as monte_carlo
    from learners.td import learner

    recorder = Recorder()
    undo = recorder.install()
    previous = learner.FUSED, monte_carlo.FUSED
    learner.FUSED = monte_carlo.FUSED = fused
    try:
        with tempfile.TemporaryDirectory() as out:
            train_population(cfg, Path(out))
    finally:
        learner.FUSED, monte_carlo.FUSED = previous
        undo()
    last = max(e for e in recorder.seconds if recorder.steps[e])
    calls = recorder.calls[last]
    return {"seconds": recorder.seconds[last], "steps": recorder.steps[last], "floor": replay(calls),
            "products": sum(c[0] == "gemm" for c in calls), "fused": recorder.fused}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=at_most(1_000), nargs="+", default=[1, 5, 25],
                        help="population sizes R (at most 1,000, a population's ceiling)")
    parser.add_argument("--steps", type=at_most(5_000), default=30,
                        help="gradient steps timed per off-policy learner and size (the paper's learners: one phase)")
    parser.add_argument("--learners", nargs="+", default=list(LEARNERS), choices=list(LEARNERS))
    parser.add_argument("--module", action="store_true",
                        help="also time the fused learners' steps through their TorchRL loss modules")
    args = parser.parse_args(argv)
    from learners import kernels

    if not kernels.active():
        print(f"The floor is the project's kernels' products, and they are not in use here: "
              f"{kernels.unavailable_reason() or 'numerics is not fma'}")
        return 1
    import torch

    rows = []
    for name in args.learners:
        recipe, off_policy = LEARNERS[name]
        for members in args.sizes:
            m = measure(recipe, off_policy, members, args.steps)
            runs = [(name, m)]
            if args.module and m["fused"]:  # the same step through the loss module
                runs.append((f"{name} (loss module)", measure(recipe, off_policy, members, args.steps, fused=False)))
            for label, m in runs:
                unit = m["steps"] if off_policy else 1  # per gradient step, or per update phase
                step, floor = m["seconds"] / unit * 1e3, m["floor"] / unit * 1e3
                rows.append([label, " ".join(recipe), members,
                             "step" if off_policy else f"phase ({m['steps']} steps)", f"{step:.2f}",
                             f"{step / members:.3f}", f"{floor:.2f}", f"{step / floor:.2f}x",
                             f"{m['products'] / unit:.0f}"])
    table("Each learner's update against its floor (its products alone), one thread",
          ["learner", "overrides", "R", "per", "ms (population)", "ms per member", "floor ms", "step / floor",
           "products"], rows)
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("speed.floor", main))
