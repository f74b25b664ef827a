"""What a trained run's critics think of the oracle's driving: do they rate the faster line lower?

    python -m analysis.pessimism RUN_DIR... [--episodes 2] [--seed 0] [--horizon 60] [--table pessimism.csv]
                                            [--line oracle|policy] [--compare oracle|slower|faster] [--delta 0.1]

For each run folder (or every run under a sweep's folder) of an off-policy learner whose Q-networks are
MLPs of (observation, action) (SAC, TD3, REDQ, TQC's quantiles averaged; not DroQ's, BRO's or CrossQ's
networks, nor a critic that reads the car's past or true state), the oracle (``racing.oracle``) drives
``--episodes`` episodes on the run's own track from the start states of ``--seed``, ``--seed + 1``, ...
At every state s of the oracle's line the run's Q-networks score two actions: the oracle's a* and the
run's own deterministic action pi(s). The same two are also scored by the simulator: the discounted
return (the run's own gamma) of taking the action, then following pi for ``--horizon`` steps in all
(the time limit lifted, as the critics' targets ignore it; crashes cost what they cost), batched over
every state in one ``RacingSim``.

Per run it prints the mean over the states of:

- ``critic_gap_min``: Q(s, a*) - Q(s, pi(s)) under the minimum over the Q-networks (what SAC's and TD3's
  targets read), and ``critic_gap_mean`` under their mean: below zero, the critic rates the oracle's
  action lower than the policy's own;
- ``true_gap``: the same difference in discounted return (above zero: a* is better, then following pi);
- ``spread_oracle``, ``spread_policy``: the Q-networks' standard deviation at a* and at pi(s): the
  pessimism penalty (the minimum is the mean minus this, with two networks) paid by each action;
- ``misranked``: the share of states where the true returns prefer a* but the minimum prefers pi(s);
  ``misled``: where the minimum prefers a* but the true returns prefer pi(s).

``--line policy`` takes the states of the run's own deterministic policy's episodes instead of the oracle's;
``--compare slower`` (``faster``) scores, in the oracle's action's place, the policy's own action with its
throttle lowered (raised) by ``--delta``, clipped to [-1, 1]: at a policy's own states, whether its critics
would move it to slower (faster) driving where the simulator says that loses (a', then pi, against pi). The
columns keep their names, a* standing for the action compared.

SAC's critics estimate soft values (each future step's entropy bonus included) and every critic
estimates the value of its own noisy policy, so the gaps, not the levels, are compared. Loads torch.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from engine.budget import SEED, count, real
from pathlib import Path

COLUMNS = ("run", "loss", "track", "states", "critic_gap_min", "critic_gap_mean", "true_gap", "spread_oracle",
           "spread_policy", "misranked", "misled")


def oracle_line(env, episodes: int, seed: int, policy=None) -> dict:
    """The oracle's states (the car's state and observation) and its actions over ``episodes`` episodes."""
    from racing.oracle import Oracle

    planner, sim = Oracle(seed=seed), env.unwrapped.sim
    return _line(env, episodes, seed, lambda observation: planner.act(sim, 0), planner.reset)


def policy_line(env, episodes: int, seed: int, policy) -> dict:
    """The states of ``policy``'s own ``episodes`` episodes and its actions there (``oracle_line``'s layout, the
    policy's actions under ``"oracle"``)."""
    return _line(env, episodes, seed, policy, policy.reset)


def _line(env, episodes: int, seed: int, act, reset) -> dict:
    """The car's states, observations and the actions of ``act(observation)`` over ``episodes`` episodes from the
    start states of ``seed``, ``seed + 1``, ... (``reset()`` at each episode's start)."""
    import numpy as np

    from racing.oracle import Oracle

    sim = env.unwrapped.sim
    cars, observations, actions = [], [], []
    for k in range(episodes):
        observation, _ = env.reset(seed=seed + k)
        reset()
        done = False
        while not done:
            cars.append({name: np.copy(getattr(sim, name)[0]) for name in Oracle.STATE})
            observations.append(np.asarray(observation, np.float32))
            action = act(observation)
            actions.append(action)
            observation, _, terminated, truncated, _ = env.step(action)
            done = terminated or truncated
    return {"cars": cars, "observations": np.stack(observations), "oracle": np.stack(actions)}


def compared_actions(own, line: dict, compare: str, delta: float):
    """The action scored against the policy's own ``own`` ``[N, 2]`` at each state: the oracle's (``line``'s),
    or ``own`` with its throttle lowered (``slower``) or raised (``faster``) by ``delta``, in [-1, 1]."""
    import torch

    if compare == "oracle":
        return torch.as_tensor(line["oracle"], dtype=torch.float32)
    out = own.clone()
    out[:, 0] = (out[:, 0] + (delta if compare == "faster" else -delta)).clamp(-1.0, 1.0)
    return out


def discounted_returns(sim, line: dict, first_actions, policy, gamma: float, horizon: int):
    """The discounted return of taking ``first_actions[i]`` at the oracle's state i and then following
    ``policy`` (``Policy.actions``) for ``horizon`` steps in all: one batched ``RacingSim`` on ``sim``'s
    track, the time limit lifted (the step counter restarts at 0), stopped where an episode ends."""
    import numpy as np
    import torch

    from racing.oracle import Oracle
    from racing.sim import RacingSim

    n = len(line["cars"])
    cars = RacingSim(n, None, sim.config, nearest_ray=sim.nearest_ray, track=sim.tracks[0])
    cars.seed(0)
    cars.reset()
    for name in Oracle.STATE:
        getattr(cars, name)[:] = np.array([state[name] for state in line["cars"]])
    cars.t[:] = 0
    cars.finished[:] = False
    total, alive, discount = np.zeros(n), np.ones(n, dtype=bool), 1.0
    actions = np.asarray(first_actions, dtype=np.float64)
    for step in range(horizon):
        reward, terminated, truncated, _ = cars.step(actions[:, 0], actions[:, 1])
        total += np.where(alive, discount * reward, 0.0)
        alive &= ~(np.asarray(terminated) | np.asarray(truncated))
        discount *= gamma
        if not alive.any():
            break
        observations = torch.as_tensor(cars.observe(), dtype=torch.float32)
        actions = policy.actions(observations).double().numpy()
    return total


def load_critics(run: Path, settings: dict):
    """The run's Q-networks as one stacked network (``[Q, B, obs + action] -> [Q, B, outputs]``): each
    Q-network's solo weights in ``critic.pt`` are one row of the stack; ``RunFolderError`` for critics
    this analysis does not read."""
    from engine.checkpoint import load_tensors
    from engine.limits import weights_limit
    from engine.outputs import RunFolderError
    from learners.networks import StackedCriticNet, load_member_state_dict
    from racing.config import RacingConfig

    td = settings["algo"].get("td") or {}
    if settings["env"].get("past_steps") or td.get("critic_history") or td.get("privileged_critic"):
        raise RunFolderError(f"{run}: its critics read more than (observation, action) (past steps, the car's "
                             "past or true state); this analysis reads critics of (observation, action) only")
    if td.get("observation_norm"):
        raise RunFolderError(f"{run}: its critics read normalised observations (algo.td.observation_norm); this "
                             "analysis reads critics of the observation as the simulator gives it")
    try:
        limit = weights_limit(settings["network"], "critic")
        state = {k.removeprefix("module."): v for k, v in load_tensors(run / "critic.pt", "critic", limit=limit).items()}
    except ValueError as err:
        raise RunFolderError(str(err)) from None
    layer = re.compile(r"net\.layers\.(\d+)\.(weight|bias)")
    if not state or not all(layer.fullmatch(k) for k in state):
        raise RunFolderError(f"{run}: its Q-networks ({settings['algo']['loss']}) are not MLPs of network.critic_hidden "
                             "of (observation, action); this analysis reads those critics only")
    layers = sorted({int(layer.fullmatch(k).group(1)) for k in state})
    first, last = state[f"net.layers.{layers[0]}.weight"], state[f"net.layers.{layers[-1]}.weight"]
    network, obs_size = settings["network"], RacingConfig(**settings["env"].get("options", {})).obs_size
    if first.shape[-1] != obs_size + 2:
        raise RunFolderError(f"{run}: its critic ({settings['algo']['loss']}) reads {first.shape[-1]} inputs, not the "
                             f"observation and the action ({obs_size + 2}): a value network of the state (the paper's "
                             "learners', NAF's, Trust-PCL's); this analysis reads Q-networks of (observation, action)")
    critics = StackedCriticNet(first.shape[0], obs_size + 2, network["critic_hidden"], network["activation"],
                               outputs=last.shape[1])
    try:
        load_member_state_dict(critics, slice(None), state)
    except (ValueError, RuntimeError):
        raise RunFolderError(f"{run / 'critic.pt'}: its Q-networks are not MLPs of network.critic_hidden (DroQ's, "
                             "BRO's or CrossQ's networks); this analysis reads MLP critics only") from None
    return critics


def measure(run: Path, episodes: int, seed: int, horizon: int, line_of: str = "oracle", compare: str = "oracle",
            delta: float = 0.1) -> dict:
    import numpy as np
    import torch

    from engine.evaluation import load_policy, make_env, own_track
    from engine.outputs import RunFolderError

    policy, settings = load_policy(run)
    critics = load_critics(run, settings)
    env = make_env(settings, own_track(settings))
    if horizon >= env.unwrapped.sim.config.max_steps:
        raise RunFolderError(f"{run}: --horizon must be below the episode's {env.unwrapped.sim.config.max_steps} "
                             f"steps, got {horizon}")
    line = (oracle_line if line_of == "oracle" else policy_line)(env, episodes, seed, policy)
    observations = torch.as_tensor(line["observations"])
    own = policy.actions(observations)
    oracle = compared_actions(own, line, compare, delta)
    networks = next(critics.parameters()).shape[0]
    with torch.no_grad():
        def values(actions):  # [Q, N]: each Q-network's value (a quantile critic's mean over its quantiles)
            x = torch.cat([observations, actions], -1).expand(networks, *observations.shape[:1], -1)
            return critics(x).mean(-1).double()
        at_oracle, at_own = values(oracle), values(own)
    gamma = float(settings["gamma"])
    sim = env.unwrapped.sim
    first = line["oracle"] if compare == "oracle" else oracle.double().numpy()
    true_oracle = discounted_returns(sim, line, first, policy, gamma, horizon)
    true_own = discounted_returns(sim, line, own.double().numpy(), policy, gamma, horizon)
    env.close()
    gap_min = (at_oracle.min(0)[0] - at_own.min(0)[0]).numpy()
    true_gap = true_oracle - true_own
    track = own_track(settings)
    return {"run": str(run), "loss": settings["algo"]["loss"], "track": track if isinstance(track, int) else str(track),
            "states": len(true_gap),
            "critic_gap_min": round(float(gap_min.mean()), 4),
            "critic_gap_mean": round(float((at_oracle.mean(0) - at_own.mean(0)).mean()), 4),
            "true_gap": round(float(true_gap.mean()), 4),
            "spread_oracle": round(float(at_oracle.std(0, correction=0).mean()), 4),
            "spread_policy": round(float(at_own.std(0, correction=0).mean()), 4),
            "misranked": round(float(np.mean((true_gap > 0) & (gap_min < 0))), 4),
            "misled": round(float(np.mean((true_gap < 0) & (gap_min > 0))), 4)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", type=Path, nargs="+", help="run folders, or sweep folders holding them")
    parser.add_argument("--episodes", type=count(1, 100), default=2, help="oracle episodes per run (default 2; ~5 s each)")
    parser.add_argument("--seed", type=SEED, default=0, help="the first start state's seed (default 0)")
    parser.add_argument("--horizon", type=count(1, 199), default=60,
                        help="steps of each true return (default 60: gamma 0.9 leaves 0.2%% of the value beyond)")
    parser.add_argument("--table", type=Path, default=None, help="also write the rows as CSV")
    parser.add_argument("--line", choices=("oracle", "policy"), default="oracle",
                        help="whose episodes' states are scored: the oracle's (default) or the run's own policy's")
    parser.add_argument("--compare", choices=("oracle", "slower", "faster"), default="oracle",
                        help="the action scored against the policy's own: the oracle's (default), or the policy's with "
                             "its throttle lowered or raised by --delta")
    parser.add_argument("--delta", type=real(0, 2), default=0.1, help="the throttle change of --compare slower/faster "
                                                                   "(default 0.1)")
    args = parser.parse_args(argv)
    from engine.processes import check_start_seeds
    from engine.tool_output import check_outputs

    check_outputs(parser, reads=args.paths, table=args.table)
    check_start_seeds(parser, args.seed, args.episodes)
    if args.line == "policy" and args.compare == "oracle":
        parser.error("--line policy scores the policy's own actions; compare them with --compare slower or faster")
    if not 0 < args.delta <= 2:  # also refuses nan
        parser.error(f"--delta must be a throttle change in (0, 2], got {args.delta}")
    from engine import numerics
    from engine.outputs import RunFolderError
    from engine.rundir import runs_numerics
    from engine.runset import read_runs

    try:
        runs = read_runs(args.paths, say="pessimism").runs  # each run once (links, copies)
        numerics.apply(runs_numerics(runs))  # before torch loads: the runs' own numerics
    except (RunFolderError, numerics.NumericsError) as err:
        print(f"pessimism: {err}", file=sys.stderr)
        return 2
    rows, skipped = [], 0
    for run in runs:  # a run this analysis cannot read is named and skipped; the others are measured
        try:
            rows.append(measure(run, args.episodes, args.seed, args.horizon, args.line, args.compare, args.delta))
        except RunFolderError as err:
            print(f"pessimism: skipped {err}", file=sys.stderr)
            skipped += 1
    if not rows:
        return 2
    print("| " + " | ".join(COLUMNS) + " |")
    print("|" + "---|" * len(COLUMNS))
    for row in rows:
        print("| " + " | ".join(str(row[c]) for c in COLUMNS) + " |")
    if len(rows) > 1:
        means = {c: round(math.fsum(r[c] for r in rows) / len(rows), 4) for c in COLUMNS[4:]}
        print("| mean | | | " + str(sum(r["states"] for r in rows)) + " | "
              + " | ".join(str(means[c]) for c in COLUMNS[4:]) + " |")
    if args.table is not None:
        from engine.outputs import write_table

        write_table(args.table, rows)
    return 2 if skipped else 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("analysis.pessimism", main))
