"""Environment speed: steps per second of every implementation, in one process.

    python speed/env_speed.py [--seconds 2]

Workload: uniformly random actions in [-1, 1] on paper track 2067791, episodes of 200
steps (the reset is timed too). One car takes the simulator's scalar path (plain Python
floats over the same tables, ``racing.physics.step_car``); more cars the batched kernels. Each row runs for about ``--seconds`` and reports steps
per second per car, as a ratio against the plain-Python scalar baseline run here (first
crossing, the reference's rule) and against its nearest-crossing variant (every segment
scanned). Ratios are what to compare across machines, not absolute numbers.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")

from engine.budget import count, real
from engine import numerics  # noqa: E402

numerics.apply(numerics.DEFAULT)  # before torch loads (engine/numerics.py)

import gymnasium as gym  # noqa: E402
import torch  # noqa: E402

import racing  # noqa: E402
from speed.scalar_racing import ScalarRacing  # noqa: E402

TRACK = racing.PAPER_TRACK_SEEDS[0]
EPISODE = 200


def timed(step, seconds: float) -> float:
    """Calls of ``step(k)`` per second, in whole episodes, after one warm-up episode."""
    for k in range(EPISODE):
        step(k)
    calls, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        for k in range(EPISODE):
            step(k)
        calls += EPISODE
    return calls / (time.perf_counter() - start)


def scalar(nearest: bool, seconds: float) -> float:
    car = ScalarRacing(TRACK, nearest=nearest)
    car.reset()
    actions = np.random.default_rng(0).uniform(-1, 1, (EPISODE, 2)).tolist()

    def step(k):
        car.step(*actions[k])
        if k == EPISODE - 1:
            car.reset()

    return timed(step, seconds)


def gymnasium_env(seconds: float, nearest: bool = False) -> float:
    env = gym.make(racing.ENV_ID, track_seed=TRACK, nearest_ray=nearest)
    env.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1, 1, (EPISODE, 2)).astype(np.float32)

    def step(k):
        _, _, terminated, truncated, _ = env.step(actions[k])
        if terminated or truncated:
            env.reset()

    return timed(step, seconds)


def gymnasium_vector(n: int, seconds: float, mode: str) -> float:
    """``gym.make_vec`` of ``n`` cars: the native vector env (``vector_entry_point``) or Gymnasium's
    ``SyncVectorEnv`` of ``n`` single envs (``sync``); both autoreset on their own."""
    env = gym.make_vec(racing.ENV_ID, num_envs=n, vectorization_mode=mode, track_seed=TRACK)
    env.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1, 1, (EPISODE, n, 2)).astype(np.float32)

    def step(k):
        env.step(actions[k])

    return timed(step, seconds) * n


def torchrl_env(n: int, seconds: float) -> float:
    env = racing.RacingTorchEnv(n, TRACK)
    env.set_seed(0)
    actions = torch.rand(EPISODE, n, 2, generator=torch.Generator().manual_seed(0)) * 2 - 1
    state = {"td": env.reset()}

    def step(k):
        td = state["td"]
        td["action"] = actions[k]
        _, state["td"] = env.step_and_maybe_reset(td)

    return timed(step, seconds) * n


def torchrl_tensors(n: int, seconds: float) -> float:
    """The lean tensor path the direct collector uses (``step_tensors``, resets of finished cars)."""
    env = racing.RacingTorchEnv(n, TRACK)
    env.set_seed(0)
    actions = torch.rand(EPISODE, n, 2, generator=torch.Generator().manual_seed(0)) * 2 - 1
    env.reset_tensors()

    def step(k):
        out = env.step_tensors(actions[k])
        if out["done"].any():
            env.reset_tensors(out["done"])

    return timed(step, seconds) * n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=real(0.01, 3600), default=2.0, help="time per row")
    parser.add_argument("--max-cars", type=count(1, 1_000_000), default=4096, help="leave out the rows of more cars than this")
    args = parser.parse_args()

    first = scalar(False, args.seconds)
    rows = [("scalar Python, first crossing (baseline)", 1, first),
            ("scalar Python, nearest crossing", 1, scalar(True, args.seconds)),
            ("Gymnasium env (gym.make)", 1, gymnasium_env(args.seconds)),
            ("Gymnasium env (gym.make), nearest_ray=True", 1, gymnasium_env(args.seconds, nearest=True)),
            ("TorchRL env, step_tensors", 1, torchrl_tensors(1, args.seconds))]
    for n in (n for n in (8, 64, 1024) if n <= args.max_cars):
        rows.append(("Gymnasium SyncVectorEnv of single envs (make_vec, sync)", n,
                     gymnasium_vector(n, args.seconds, "sync")))
        rows.append(("Gymnasium native vector env (make_vec)", n, gymnasium_vector(n, args.seconds, "vector_entry_point")))
    for n in (n for n in (1, 64, 1024, 4096) if n <= args.max_cars):
        rows.append(("TorchRL env, step_and_maybe_reset", n, torchrl_env(n, args.seconds)))
    nearest = rows[1][2]
    print(f"numpy {np.__version__}, torch {torch.__version__} ({torch.get_num_threads()} thread), "
          f"{os.cpu_count()} cores; random actions on track {TRACK}\n")
    print("| implementation | cars | car-steps/s | vs scalar baseline | vs scalar nearest |")
    print("|---|---:|---:|---:|---:|")
    for name, n, rate in rows:
        print(f"| {name} | {n} | {rate:,.0f} | {rate / first:.2f}x | {rate / nearest:.1f}x |")


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("speed.env_speed", main))
