"""Where a planning run's plans go wrong: what its model predicted along the episodes it drove, what its
Q-values promised where the plans end, and what other planner settings do with the same networks.

    python -m analysis.planner RUN_DIR... [--episodes 5] [--seed 0] [--variant KEY=VALUE[,KEY=VALUE...]]...
                                          [--variant prior] [--processes 2] [--table planner.csv]

Each run (``algo=tdmpc2`` with planning; or every such run under a sweep's folder, others skipped with a line
and exit status 2) drives ``--episodes``
episodes on its own track from the start states of ``--seed``, ``--seed + 1``, ... with its deterministic
policy as ``evaluate.py`` drives it (MPPI without the executed action's noise, its draws seeded 0 at every
episode's start), then with each ``--variant``: the same saved networks planning under other settings
(``learners.latent.PlanOptions``' fields: ``horizon``, ``samples``, ``policy_samples``, ``elites``,
``iterations``, ``temperature``, ``min_std``, ``max_std``), or ``prior``: the policy prior's tanh(loc)
without planning. Nothing is trained.

After each episode, the run's model reads what happened (``readout``): from the latent state of every step t
it rolls its dynamics along the actions the car then took and predicts the rewards of steps t, t + 1, ...
A crash (a step on which the car left the track, as the simulator counts them) at step c is *foreseen at k* when
the reward the model predicted for step c from step c - k is below minus half the penalty; a false alarm is such a
prediction for a step without a crash. The value the plan's scoring gives what the car did, V(t) (the
predicted rewards of ``horizon`` steps, then gamma^horizon x the Q-networks' mean at the rolled state and the
prior's action), is compared with the discounted return the car then received, G(t) (the run's gamma), over
the ten steps before each crash and over the other steps (both up to 40 steps before the episode's end,
where G(t) is cut short by the time limit).

Where a crash is decided is tried on the true simulator: from the car's state ``k`` steps before the crashing
step (k in 0, 2, 5, 10), whether some constant action of a 9 x 9 grid (throttle and steering in -1, -0.75, ...,
1) held for k + 1 steps keeps the car on the track (a lower bound on what a driver could still do there).

Per run and variant a row: ``mean_reward``, ``crashes_per_episode``, ``crashes`` (their number),
``foreseen_0``..``foreseen_2`` (share of crashes foreseen at k = 0, 1, 2: from the state before the crashing
step, one and two steps earlier), ``avoidable_0``..``avoidable_10`` (share of crashes some constant action
avoids from k steps before), ``model_way_out_0`` (share of crashes where the model predicts, from the state
before the crashing step, a reward above minus half the penalty for some action of the grid), ``false_alarms``
(share of the other steps' predictions at k = 0..2 below minus half the penalty), ``reward_error`` (mean
absolute error of the predicted reward at k = 0..horizon - 1 on steps without a crash),
``value_error_before_crash`` and ``value_error_elsewhere`` (mean V(t) - G(t): positive is optimism). The
read-out always uses the run's own horizon; a variant changes only how the car is driven.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, field, replace
from engine.budget import PROCESSES, SEED, check_items, check_work, count, real
from pathlib import Path

COLUMNS = ("run", "track", "variant", "episodes", "mean_reward", "crashes_per_episode", "crashes", "foreseen_0",
           "foreseen_1", "foreseen_2", "avoidable_0", "avoidable_2",
           "avoidable_5", "avoidable_10", "model_way_out_0", "false_alarms", "reward_error", "value_error_before_crash",
           "value_error_elsewhere")
AS_TRAINED = "as trained"
PRIOR = "prior"
LOOKAHEAD = 3  # foresight is read at k = 0, 1, 2
BEFORE_CRASH = 10  # the steps before a crash whose values are read apart
CUT_SHORT = 40  # steps before the episode's end whose discounted return the time limit cuts (0.9^40 ~ 1.5%)
LIMITS = {"horizon": (1, 50), "samples": (2, 4096), "policy_samples": (0, 4095), "elites": (1, 4096),
          "iterations": (1, 50), "temperature": (1e-6, 1e6), "min_std": (1e-6, 10.0), "max_std": (1e-6, 10.0)}


class VariantError(ValueError):
    """A ``--variant`` that names no planner setting or gives it a value out of range."""


def parse_variant(text: str) -> dict:
    """``--variant``'s text as {field: value} (``{}`` for ``prior``); ``VariantError`` saying what was expected."""
    if text.strip() == PRIOR:
        return {}
    out = {}
    for part in text.split(","):
        key, sep, value = part.partition("=")
        key = key.strip()
        if not sep or key not in LIMITS:
            raise VariantError(f"--variant {text!r}: expected 'prior' or KEY=VALUE[,KEY=VALUE...] with KEY one of "
                               f"{', '.join(LIMITS)}")
        if key in out:
            raise VariantError(f"--variant {text!r}: {key} given twice")
        low, high = LIMITS[key]
        try:
            number = int(value) if isinstance(low, int) else float(value)
        except ValueError:
            raise VariantError(f"--variant {text!r}: {key} must be {'an integer' if isinstance(low, int) else 'a number'}"
                               f", got {value!r}") from None
        if not (low <= number <= high):  # also refuses nan
            raise VariantError(f"--variant {text!r}: {key} must be in [{low:g}, {high:g}], got {value.strip()}")
        out[key] = number
    return out


def planned_options(options, changes: dict):
    """The run's ``PlanOptions`` with ``changes``; ``VariantError`` if they do not fit together."""
    new = replace(options, **changes)
    if new.policy_samples >= new.samples:
        raise VariantError(f"policy_samples ({new.policy_samples}) must be below samples ({new.samples})")
    if new.elites > new.samples:
        raise VariantError(f"elites ({new.elites}) must be at most samples ({new.samples})")
    if new.max_std < new.min_std:
        raise VariantError(f"max_std ({new.max_std:g}) is below min_std ({new.min_std:g})")
    return new


@dataclass
class Episode:
    """What one episode's car saw, did and got (the network's inputs as the policy read them)."""

    observations: list = field(default_factory=list)
    actions: list = field(default_factory=list)
    rewards: list = field(default_factory=list)
    crashed: list = field(default_factory=list)
    cars: list = field(default_factory=list)  # the car's state before each step (``CAR``)


CAR = ("x", "y", "theta", "speed", "checkpoint", "t")
EARLIER = (0, 2, 5, 10)  # a crash's avoidability is tried from these many steps before its step
GRID = 9  # throttles x steerings of the constant actions tried at a crash (-1, -0.75, ..., 1 each)


def drive(policy, env, seed: int) -> Episode:
    """One episode of ``policy`` (``engine.evaluation.Policy``) from the start state of ``seed``, recorded: a step
    crashed when the simulator counted the car leaving the track on it."""
    import numpy as np

    from engine.evaluation import drive_episode

    episode = Episode()
    sim = env.unwrapped.sim

    def recorded(env, observation):
        sim = env.unwrapped.sim
        episode.cars.append({name: getattr(sim, name)[0].item() for name in CAR})
        action = np.asarray(policy(observation), dtype=np.float64)
        episode.observations.append(np.asarray(observation, dtype=np.float32))
        episode.actions.append(action.astype(np.float32))
        return action

    original_step = env.step

    def step(action):
        before = int(sim.crashes[0])
        out = original_step(action)
        episode.rewards.append(float(out[1]))
        episode.crashed.append(int(sim.crashes[0]) > before)
        return out

    env.step = step
    try:
        drive_episode(recorded, env, seed, reset=policy.reset)
    finally:
        del env.step
    return episode


def grid_actions():
    """The constant actions tried at a crash ``[GRID * GRID, 2]``."""
    import numpy as np

    levels = np.linspace(-1.0, 1.0, GRID)
    return np.stack(np.meshgrid(levels, levels, indexing="ij"), -1).reshape(-1, 2)


def avoidable(sim, car: dict, steps: int) -> bool:
    """Whether some constant action of the grid, held ``steps`` steps from the car state ``car`` on ``sim``'s track,
    keeps the car on the track throughout (the true simulator: a fresh ``RacingSim`` of one car per action)."""
    from racing.sim import RacingSim

    actions = grid_actions()
    trial = RacingSim(len(actions), sim.track_seeds[0], sim.config, sim.nearest_ray, track=sim.file_track)
    trial.seed(0)
    trial.reset()
    for name in CAR:
        getattr(trial, name)[:] = car[name]
    trial.crashes[:] = 0
    for _ in range(steps):
        _, terminated, _, _ = trial.step(actions[:, 0].copy(), actions[:, 1].copy())
        if terminated.any():  # past the last checkpoint: that car is safe from here on
            break
    return bool((trial.crashes == 0).any())


def predictions(actor, episode: Episode, gamma: float):
    """Along ``episode``, what the planning ``actor`` (a ``learners.latent.PlanningActor``) predicted: (the latent
    states ``[1, T, L]``, ``predicted[k, t]`` the reward of step t + k its model predicted from step t along the
    actions taken (k < max(horizon, 3); nan past the episode's end), ``value[t]`` the value the plan's scoring
    (``learners.latent.trajectory_values``) gives the actions taken over its horizon from t with the prior's
    action at its end (nan where the episode ends first), ``returns[t]`` the discounted return received)."""
    import numpy as np
    import torch

    model, support, horizon = actor.model, actor.support, actor.options.horizon
    observations = torch.as_tensor(np.stack(episode.observations)).unsqueeze(0)  # [1, T, obs]
    actions = torch.as_tensor(np.stack(episode.actions)).unsqueeze(0).clamp(-1.0, 1.0)
    rewards = np.asarray(episode.rewards)
    steps = len(rewards)
    norm = getattr(actor.net, "norm", None)
    reach = max(horizon, LOOKAHEAD)
    predicted = np.full((reach, steps), np.nan)
    value = np.full(steps, np.nan)
    with torch.no_grad():
        z = model.encode(norm(observations) if norm is not None else observations)  # [1, T, L]
        state, discount, total = z, 1.0, torch.zeros(1, steps)
        for k in range(min(reach, steps)):
            count = steps - k  # the states that still have an action k steps on
            logits, state = model.step(state[:, :count], actions[:, k:k + count])
            r = support.value(logits)[..., 0]
            predicted[k, :count] = r[0].numpy()
            if k < horizon:
                total = total[:, :count] + discount * r
                discount *= gamma
                if k == horizon - 1:
                    loc, _ = model.pi(state)
                    q = actor.q_value(state, torch.tanh(loc))[..., 0]
                    value[:count] = (total + discount * q)[0].numpy()
    returns = np.zeros(steps)
    running = 0.0
    for t in range(steps - 1, -1, -1):
        running = rewards[t] + gamma * running
        returns[t] = running
    return z, predicted, value, returns


def readout(actor, episode: Episode, gamma: float, penalty: float, sim=None) -> dict:
    """What the model ``actor`` (a ``learners.latent.PlanningActor``: its model, Q-networks and horizon) predicted
    along ``episode`` (``predictions``; the module's docstring): sums and counts to pool over episodes. ``sim``:
    the simulator the episode drove (its track and config), where a crash's avoidability is tried; None: not tried."""
    import numpy as np
    import torch

    model, support, horizon = actor.model, actor.support, actor.options.horizon
    z, predicted, value, returns = predictions(actor, episode, gamma)
    rewards = np.asarray(episode.rewards)
    crashed = np.asarray(episode.crashed, dtype=bool)
    steps = len(rewards)
    alarm = predicted[:LOOKAHEAD] < -penalty / 2  # [k, t]: step t + k foreseen as a crash from t
    crash_steps = np.flatnonzero(crashed)
    foreseen = [0] * LOOKAHEAD
    for c in crash_steps:
        for k in range(LOOKAHEAD):
            if c - k >= 0 and alarm[k, c - k]:
                foreseen[k] += 1
    ways_out = [0] * len(EARLIER)  # crashes some constant action avoided, from k steps before (EARLIER)
    model_way_out = 0  # crashes where the model predicted some action of the grid avoids it (the last step)
    if len(crash_steps):
        grid = torch.as_tensor(grid_actions(), dtype=torch.float32)
        with torch.no_grad():
            c, g = len(crash_steps), len(grid)
            last = z[:, torch.as_tensor(crash_steps)]  # [1, C, L]: the states before the crashing steps
            logits, _ = model.step(last.unsqueeze(2).expand(-1, -1, g, -1).reshape(1, c * g, -1),
                                   grid.repeat(c, 1).unsqueeze(0))
            best = support.value(logits)[..., 0].reshape(c, g).amax(-1).numpy()  # [C]
        model_way_out = int((best > -penalty / 2).sum())
        if sim is not None:
            for c in crash_steps:
                for i, k in enumerate(EARLIER):
                    if c >= k:
                        ways_out[i] += avoidable(sim, episode.cars[c - k], k + 1)
    quiet_alarms = quiet = 0
    errors, error_count = 0.0, 0
    for k in range(LOOKAHEAD):
        target = np.arange(k, steps)  # the steps t + k
        calm = ~crashed[target]
        quiet_alarms += int(alarm[k, :steps - k][calm].sum())
        quiet += int(calm.sum())
    for k in range(horizon):
        target = np.arange(k, steps)
        calm = ~crashed[target]
        errors += float(np.abs(predicted[k, :steps - k] - rewards[target])[calm].sum())
        error_count += int(calm.sum())
    near = np.zeros(steps, dtype=bool)
    for c in crash_steps:
        near[max(0, c - BEFORE_CRASH):c] = True
    usable = np.arange(steps) < steps - CUT_SHORT
    gap = value - returns
    return {"reward": float(rewards.sum()), "crashes": len(crash_steps), "foreseen": foreseen,
            "ways_out": ways_out, "model_way_out": model_way_out,
            "alarms": quiet_alarms, "quiet": quiet, "errors": errors, "error_count": error_count,
            "near_gap": float(gap[near & usable].sum()), "near": int((near & usable).sum()),
            "far_gap": float(gap[~near & usable].sum()), "far": int((~near & usable).sum())}


def _ratio(a: float, b: float) -> float:
    return round(a / b, 4) if b else math.nan


def pooled(run: str, track, variant: str, parts: list[dict]) -> dict:
    """One row from an episode's ``readout`` each."""
    crashes = sum(p["crashes"] for p in parts)
    return {"run": run, "track": track, "variant": variant, "episodes": len(parts),
            "mean_reward": round(math.fsum(p["reward"] for p in parts) / len(parts), 4),
            "crashes_per_episode": round(crashes / len(parts), 3), "crashes": crashes,
            **{f"foreseen_{k}": _ratio(sum(p["foreseen"][k] for p in parts), crashes) for k in range(LOOKAHEAD)},
            **{f"avoidable_{k}": _ratio(sum(p["ways_out"][i] for p in parts), crashes) for i, k in enumerate(EARLIER)},
            "model_way_out_0": _ratio(sum(p["model_way_out"] for p in parts), crashes),
            "false_alarms": _ratio(sum(p["alarms"] for p in parts), sum(p["quiet"] for p in parts)),
            "reward_error": _ratio(sum(p["errors"] for p in parts), sum(p["error_count"] for p in parts)),
            "value_error_before_crash": _ratio(sum(p["near_gap"] for p in parts), sum(p["near"] for p in parts)),
            "value_error_elsewhere": _ratio(sum(p["far_gap"] for p in parts), sum(p["far"] for p in parts))}


SUMMARY_COLUMNS = ("variant", "runs", "group", "crashes_per_episode", "mean_reward", "gain", "gain_low", "gain_high",
                   "foreseen_0", "foreseen_1", "foreseen_2", "avoidable_0", "avoidable_2", "avoidable_5", "avoidable_10",
                   "model_way_out_0", "value_gap", "value_gap_low", "value_gap_high")
POOLED = ("foreseen_0", "foreseen_1", "foreseen_2", "avoidable_0", "avoidable_2", "avoidable_5", "avoidable_10",
          "model_way_out_0")


def summary_rows(rows: list[dict], crashing: float) -> list[dict]:
    """Per variant, over the runs whose policy as trained leaves the track at least ``crashing`` times an episode
    (group ``crashing``), the others (``other``) and all: the crashes an episode, the mean score and its gain over
    the policy as trained (paired by run, 95% t interval), each crash share pooled over the group's crashes, and
    ``value_gap``: value_error_before_crash - value_error_elsewhere, its mean over the group's runs with crashes
    and 95% t interval."""
    from analysis.factors import t_interval

    trained = {r["run"]: r for r in rows if r["variant"] == AS_TRAINED}
    groups = {"crashing": {run for run, r in trained.items() if float(r["crashes_per_episode"]) >= crashing}}
    groups["other"] = set(trained) - groups["crashing"]
    groups["all"] = set(trained)
    out = []
    for variant in dict.fromkeys(r["variant"] for r in rows):
        for group, runs in groups.items():
            chosen = [r for r in rows if r["variant"] == variant and r["run"] in runs]
            if not chosen:
                continue
            crashes = sum(int(r["crashes"]) for r in chosen)
            episodes = sum(int(r["episodes"]) for r in chosen)
            row = {"variant": variant, "runs": len(chosen), "group": group,
                   "crashes_per_episode": round(crashes / episodes, 3),
                   "mean_reward": round(math.fsum(float(r["mean_reward"]) for r in chosen) / len(chosen), 2)}
            gain = t_interval([float(r["mean_reward"]) - float(trained[r["run"]]["mean_reward"]) for r in chosen])
            row.update(zip(("gain", "gain_low", "gain_high"), (round(g, 2) for g in gain)))
            for column in POOLED:  # shares of the group's crashes
                row[column] = _ratio(math.fsum(float(r[column]) * int(r["crashes"]) for r in chosen if int(r["crashes"])),
                                     crashes)
            gaps = [float(r["value_error_before_crash"]) - float(r["value_error_elsewhere"]) for r in chosen
                    if not math.isnan(float(r["value_error_before_crash"]))]
            gap = t_interval(gaps) if gaps else (math.nan,) * 3
            row.update(zip(("value_gap", "value_gap_low", "value_gap_high"), (round(g, 3) for g in gap)))
            out.append(row)
    return out


def planning_actor(policy, run):
    """The run's ``PlanningActor`` inside its deterministic ``policy``; ``RunFolderError`` if it does not plan."""
    from engine.outputs import RunFolderError
    from learners.latent import PlanningActor

    if not isinstance(policy.net, PlanningActor) or policy.history is not None:
        raise RunFolderError(f"{run}: not a planning run (algo=tdmpc2 with algo.tdmpc2.planning: true and no "
                             "env.past_steps): its policy has no model that plans")
    return policy.net


def readable(run: Path, variants: list[str]) -> tuple:
    """The run's (policy, settings, planning actor, {variant: its PlanOptions}) if this read-out can drive it under
    every variant; ``RunFolderError`` saying why not (not a planning run, no crash penalty) and ``VariantError``
    naming the variant and the run that do not fit together. Nothing is driven."""
    from engine.evaluation import load_policy
    from engine.outputs import RunFolderError
    from racing.config import RacingConfig

    policy, settings = load_policy(run)
    actor = planning_actor(policy, run)
    penalty = RacingConfig(**settings["env"].get("options", {})).crash_penalty
    if penalty <= 0:
        raise RunFolderError(f"{run}: trained with env.options.crash_penalty={penalty:g}; the read-out knows a predicted "
                             "crash by its penalty (a reward below minus half of it), so it reads runs with a penalty")
    options = {}
    for name in variants:
        changes = parse_variant(name)
        if changes:
            try:
                options[name] = planned_options(actor.options, changes)
            except VariantError as err:
                raise VariantError(f"--variant {name.strip()!r} does not fit {run}: {err}") from None
    return policy, settings, actor, options


def run_rows(run: Path, variants: list[str], episodes: int, seed: int) -> list[dict]:
    """The rows of one run: as trained, then each variant (``--variant``'s texts; ``readable`` checks them)."""
    from engine.evaluation import Policy, make_env, own_track
    from learners.latent import PlanningActor

    policy, settings, actor, options = readable(run, variants)
    track = own_track(settings)
    env = make_env(settings, track)
    penalty, gamma = float(env.unwrapped.config.crash_penalty), actor.options.gamma
    rows = []
    try:
        for name in [AS_TRAINED, *variants]:
            if name.strip() == PRIOR:
                driver = Policy(actor.net, stacked=True)  # the prior's tanh(loc), behind the run's observation norm
            elif name in options:
                driver = Policy(PlanningActor(actor.net, actor.qvalues, options[name], actor.support).eval(), stacked=True)
            else:
                driver = policy
            parts = [readout(actor, drive(driver, env, seed + k), gamma, penalty, env.unwrapped.sim) for k in range(episodes)]
            rows.append(pooled(str(run), track, name.strip(), parts))
    finally:
        env.close()
    return rows


def _one(args: tuple) -> list[dict]:
    return run_rows(*args)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", type=Path, nargs="+", help="planning runs' folders, or sweep folders holding them")
    parser.add_argument("--episodes", type=count(1, 1000), default=5, help="episodes per run and variant (default 5)")
    parser.add_argument("--seed", type=SEED, default=0, help="the first start state's seed (default 0)")
    parser.add_argument("--variant", action="append", default=[], metavar="KEY=VALUE[,...]|prior",
                        help="also drive with these planner settings (repeatable), or 'prior': the prior without planning")
    parser.add_argument("--processes", type=PROCESSES, default=1, help="runs driven at once, one process each")
    parser.add_argument("--table", type=Path, default=None, help="also write the rows as CSV")
    parser.add_argument("--crashing", type=real(0, 1_000_000), default=1.0,
                        help="the summary's crashing runs leave the track at least this often an episode as trained "
                             "(default 1.0)")
    parser.add_argument("--summary", type=Path, default=None, help="also write the summary (per variant and group) as CSV")
    args = parser.parse_args(argv)
    from engine.processes import check_start_seeds
    from engine.tool_output import check_outputs

    check_outputs(parser, reads=args.paths, table=args.table, summary=args.summary)
    check_start_seeds(parser, args.seed, args.episodes)
    if args.table is not None and args.summary is not None and args.table.resolve() == args.summary.resolve():
        parser.error(f"--table and --summary name one file ({args.table}); give two")
    check_items(parser, "--variant", args.variant, 64)
    check_work(parser, 100_000, "episodes a run", variants=len(args.variant) + 1, episodes=args.episodes)
    if len({v.strip() for v in args.variant}) < len(args.variant):
        parser.error("a --variant is given twice")
    for text in args.variant:
        try:
            parse_variant(text)
        except VariantError as err:
            parser.error(str(err))
    from engine import numerics
    from engine.outputs import RunFolderError
    from engine.pool import run_jobs
    from engine.rundir import runs_numerics
    from engine.runset import read_runs

    try:
        found_runs = read_runs(args.paths, say="planner").runs  # each run once (named twice, a link, a copy)
        numerics.apply(runs_numerics(found_runs))  # before torch loads: the runs' own numerics
        runs, skipped = [], 0
        for run in found_runs:  # every run and variant checked before any driving; a run it cannot read is skipped
            try:
                readable(run, args.variant)
                runs.append(run)
            except RunFolderError as err:
                print(f"planner: skipped {err}", file=sys.stderr)
                skipped += 1
        if not runs:
            return 2
        jobs = [(run, args.variant, args.episodes, args.seed) for run in runs]
        found = run_jobs(_one, jobs, args.processes, numerics.applied())
    except (RunFolderError, VariantError, numerics.NumericsError) as err:
        print(f"planner: {err}", file=sys.stderr)
        return 2
    rows = [row for rows in found for row in rows]
    print("| " + " | ".join(COLUMNS) + " |")
    print("|" + "---|" * len(COLUMNS))
    for row in rows:
        print("| " + " | ".join(str(row[c]) for c in COLUMNS) + " |")
    summary = summary_rows(rows, args.crashing)
    print(f"\nSummary (crashing: {args.crashing:g} or more crashes an episode as trained; gain: paired by run against "
          "the policy as trained, 95% t interval; crash shares pooled over the group's crashes)")
    print("| " + " | ".join(SUMMARY_COLUMNS) + " |")
    print("|" + "---|" * len(SUMMARY_COLUMNS))
    for row in summary:
        print("| " + " | ".join(str(row[c]) for c in SUMMARY_COLUMNS) + " |")
    from engine.outputs import write_table

    if args.table is not None:
        write_table(args.table, rows)
    if args.summary is not None:
        write_table(args.summary, summary)
    return 2 if skipped else 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("analysis.planner", main))
