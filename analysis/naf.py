"""What a trained NAF run's networks say about its advantage: ``python -m analysis.naf RUN_DIR...``.

NAF's Q-function is V(s) - 1/2 (a - mu(s))^T P(s) (a - mu(s)); mu's gradient is P (a - mu), so a
curvature P that shrinks leaves mu without a gradient. For each finished NAF run folder (or a
population's folder of members) this drives the run's deterministic policy for one episode on
its own track (start state 0) and prints, over the states it visits: the trace of P (median,
lowest, highest), the same for a freshly initialised value network of the run's sizes
(``torch.Generator`` seed 0: the scale P starts at), the mean throttle and steering, the median
pre-tanh throttle (deep in tanh's tails: |u| > 3, mu's own gradient vanishes too), and the final
speed. Loads torch; reads the run's ``actor.pt`` and ``critic.pt``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def curvature(run: Path) -> dict[str, float]:
    """The figures of the module docstring for one finished NAF run."""
    import torch

    from engine.checkpoint import load_tensors
    from engine.limits import weights_limit
    from engine.evaluation import load_policy
    from engine.outputs import RunFolderError
    from learners.networks import StackedCriticNet, load_member_state_dict, reset_parameters
    from losses.naf import lower_entries, naf_precision
    from racing.config import RacingConfig
    from racing.gym_env import RacingEnv

    policy, settings = load_policy(run)
    from learners.td.naf import SPEC

    if settings["algo"]["loss"] != SPEC.name:  # NAF's networks: V, mu and the advantage's L
        raise RunFolderError(f"{run} is a run of loss {settings['algo']['loss']!r}, not {SPEC.name}")
    if settings["env"].get("past_steps"):
        raise RunFolderError(f"{run} trained with env.past_steps (its networks read past steps); this analysis reads "
                             "runs without past steps only")
    network, options = settings["network"], settings["env"].get("options", {})
    obs_size = RacingConfig(**options).obs_size

    def value_net() -> StackedCriticNet:
        return StackedCriticNet(1, obs_size, network["critic_hidden"], network["activation"],
                                outputs=1 + lower_entries(2))

    trained = value_net()
    try:
        state = load_tensors(run / "critic.pt", "critic", limit=weights_limit(network, "critic"))
    except ValueError as err:
        raise RunFolderError(str(err)) from None
    load_member_state_dict(trained, 0, {k.removeprefix("module."): v for k, v in state.items()})
    fresh = reset_parameters(value_net(), [torch.Generator().manual_seed(0)])
    env = RacingEnv(track_seed=int(settings["seed"]), **options)
    observation, _ = env.reset(seed=0)
    states, actions, pre_tanh = [], [], []
    body = policy.net[0]  # mu before its tanh
    done = False
    while not done:
        states.append(observation)
        with torch.no_grad():
            pre_tanh.append(float(body(torch.as_tensor(observation, dtype=torch.float32)[None, None])[0, 0, 0]))
        action = policy(observation)
        actions.append(action)
        observation, _, terminated, truncated, _ = env.step(action)
        done = terminated or truncated
    x = torch.as_tensor(np.array(states), dtype=torch.float32)[None]
    with torch.no_grad():
        trace = naf_precision(trained(x)[0, :, 1:], 2).diagonal(dim1=-2, dim2=-1).sum(-1)
        initial = naf_precision(fresh(x)[0, :, 1:], 2).diagonal(dim1=-2, dim2=-1).sum(-1)
    actions = np.array(actions)
    from engine.outputs import read_summary

    summary = read_summary(run)
    return {"final": summary["final_mean"], "trace_median": float(trace.median()), "trace_low": float(trace.min()),
            "trace_high": float(trace.max()), "initial_median": float(initial.median()),
            "throttle": float(actions[:, 0].mean()), "steering": float(actions[:, 1].mean()),
            "pre_tanh_throttle": float(np.median(pre_tanh)), "speed": float(states[-1][-1])}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="finished NAF run folders (or population folders)")
    args = parser.parse_args(argv)
    from engine import numerics
    from engine.outputs import RunFolderError
    from engine.rundir import runs_numerics
    from engine.runset import read_runs

    try:
        runs = read_runs(args.runs, say="naf").runs  # each path a run, or the runs below it (a population's members)
        numerics.apply(runs_numerics(runs))  # before torch loads: the runs' own numerics
    except (RunFolderError, numerics.NumericsError) as err:
        print(f"naf: {err}", file=sys.stderr)
        return 2
    print("| run | final | tr P median [lowest, highest] | tr P at initialisation | throttle | steering "
          "| pre-tanh throttle | final speed |")
    print("|---|---:|---|---:|---:|---:|---:|---:|")
    for run in runs:
        try:
            c = curvature(run)
        except RunFolderError as err:
            print(f"{run}: {err}", file=sys.stderr)
            return 1
        print(f"| {run} | {c['final']:.1f} | {c['trace_median']:.4f} [{c['trace_low']:.4f}, {c['trace_high']:.4f}] | "
              f"{c['initial_median']:.3f} | {c['throttle']:+.2f} | {c['steering']:+.2f} | "
              f"{c['pre_tanh_throttle']:+.1f} | {c['speed']:.3f} |")
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    sys.exit(run_tool("analysis.naf", main))
