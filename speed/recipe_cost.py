"""What a run of each off-policy recipe costs, measured before its sweeps are planned.

    python -m speed.recipe_cost [--sizes 3 25] [--steps 40] [--recipes sac droq ...]

For each recipe (an algorithm with its settings; ``RECIPES``) and population size R, one short
population run on the wide grid's fixed tracks (one warm-up episode, then one block of ``--steps``
gradient steps, one thread, the default numerics), and a second one of twice the steps, measure
the seconds per gradient step of the whole population (from their difference) and per collected
episode. A gradient step costs the same whatever the schedule
(its minibatch and networks do not change), so the cost of a full run follows: the recipe's
gradient steps for ``episodes`` (201) episodes times the step's cost, plus the collection. The
table gives per recipe and R: milliseconds per gradient step (population, and per member), the
CPU minutes per member for a whole run, and the hours a population of R needs on one core. Absolute
numbers depend on the machine and the hour (this one's speed drifts by 2x): plan with the ratios
between recipes, measured in one process. ``sac-module`` is SAC with its gradient step through
TorchRL's loss module instead of the fused step (``losses.sac.fused_sac_losses``, the same bits):
its row against ``sac``'s is what the fused step saves (``bro-module`` and ``droq-module`` against
``bro`` and ``droq`` likewise).
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")

from engine import numerics  # noqa: E402

numerics.apply(numerics.DEFAULT)

from speed.population_speed import member_seeds  # noqa: E402
from speed.train_speed import at_most, table  # noqa: E402
from engine.config import RunConfig  # noqa: E402
from engine.runner import train_population  # noqa: E402

RECIPES = {  # name: (overrides of the recipe, shown as given)
    "sac": ["algo=sac"],
    "sac-per": ["algo=sac", "er=prioritised"],
    "sac-module": ["algo=sac"],  # SAC's step through TorchRL's loss module (the fused step's baseline)
    "sac-nstep3": ["algo=sac", "algo.td.n_step=3"],
    "droq": ["algo=droq"],  # algo=droq's defaults (tuned: 5 updates per step)
    "droq-module": ["algo=droq"],  # DroQ's step through TorchRL's loss module
    "droq-per-5": ["algo=droq", "er=prioritised", "algo.td.updates_per_step=5.0"],  # DroQ's tuning grid (docs/tuning.md)
    "droq-per-10": ["algo=droq", "er=prioritised", "algo.td.updates_per_step=10.0"],
    "droq-per-20": ["algo=droq", "er=prioritised", "algo.td.updates_per_step=20.0"],  # DroQ's published ratio
    "bro": ["algo=bro", "er=prioritised"],
    "bro-256": ["algo=bro", "er=prioritised", "algo.td.critic_width=256"],
    "bro-module": ["algo=bro", "er=prioritised"],  # BRO's step through TorchRL's loss module
    "redq": ["algo=redq", "er=prioritised", "algo.td.updates_per_step=20.0"],  # the published: 10 Q-networks, 20 updates
    "redq-5": ["algo=redq", "er=prioritised", "algo.redq.critics=5", "algo.td.updates_per_step=20.0"],
    "redq-default": ["algo=redq", "er=prioritised"],  # algo=redq's defaults (tuned: 10 Q-networks, 5 updates per step)
    "tqc": ["algo=tqc"],
    "crossq": ["algo=crossq"],
    "td3": ["algo=td3"],
    "simbav2": ["algo=simbav2", "er=prioritised"],  # algo=simbav2's defaults (widths 64, one block)
    "simbav2-critics2": ["algo=simbav2", "er=prioritised", "algo.simbav2.critics=2"],
    "simbav2-128": ["algo=simbav2", "er=prioritised", "algo.simbav2.actor_width=128",
                    "algo.simbav2.critic_width=128"],
}


UNFUSED = {"sac-module", "bro-module", "droq-module"}  # recipes measured with learners.td.learner.FUSED off


def _timed(recipe: list[str], members: int, steps: int, episode_steps: int) -> dict:
    seeds = ",".join(map(str, member_seeds(members)))
    utd = steps / episode_steps  # one block of `steps` gradient steps before the second episode
    cfg = RunConfig.compose(*recipe, "episodes=2", "final_window=2", "algo.td.warmup_episodes=1",
                            f"algo.td.updates_per_step={utd}", "progress=false", "logger=none", "checkpoint_every=0",
                            f"seeds=[{seeds}]")
    with tempfile.TemporaryDirectory() as out:
        summary = train_population(cfg, Path(out))[0]
    return {"train": summary["time/train_s"], "episode": summary["time/rollout_s"] / 2}


def measure(recipe: list[str], members: int, steps: int, episode_steps: int = 200, fused: bool = True) -> dict:
    """Seconds per gradient step (population) and per collected episode: two short runs, of ``steps``
    and ``2 * steps`` gradient steps, whose difference leaves out what the first steps cost once
    (allocations, first calls)."""
    from learners.td import learner

    probe = RunConfig.compose(*recipe)
    previous, learner.FUSED = learner.FUSED, fused
    try:
        short, long = _timed(recipe, members, steps, episode_steps), _timed(recipe, members, 2 * steps, episode_steps)
    finally:
        learner.FUSED = previous
    extra = long["train"] - short["train"]  # None below: noise hid the step (the longer run was not slower)
    return {"step": extra / steps if extra > 0 else None, "episode": long["episode"],
            "td": probe.algo.td, "episodes": probe.episodes}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=at_most(1_000), nargs="+", default=[3, 25], help="population sizes R")
    parser.add_argument("--steps", type=at_most(5_000), default=40, help="gradient steps measured per recipe and size")
    parser.add_argument("--recipes", nargs="+", default=list(RECIPES), choices=list(RECIPES))
    args = parser.parse_args(argv)
    rows = []
    for name in args.recipes:
        for members in args.sizes:
            m = measure(RECIPES[name], members, args.steps, fused=name not in UNFUSED)
            td = m["td"]
            updates = td.updates_before(m["episodes"] - 1, 200)  # a whole run's: before its last episode
            if m["step"] is None:  # an empty measurement is not a number: say so (more --steps measure it)
                rows.append([name, " ".join(RECIPES[name]), members, f"{td.updates_per_step:g}", updates]
                            + ["n/a (noise: more --steps)"] * 4)
                continue
            seconds = updates * m["step"] + m["episodes"] * m["episode"]  # the population's
            rows.append([name, " ".join(RECIPES[name]), members, f"{td.updates_per_step:g}", updates,
                         f"{m['step'] * 1e3:.1f}", f"{m['step'] / members * 1e3:.2f}",
                         f"{seconds / members / 60:.1f}", f"{seconds / 3600:.2f}"])
    table("Cost of a whole run (201 episodes) per recipe, from a short run on one thread",
          ["recipe", "overrides", "R", "updates/step", "gradient steps", "ms/step (population)",
           "ms/step per member", "CPU min per member", "hours per population (one core)"], rows)
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("speed.recipe_cost", main))
