"""A run whose actor starts from another run's (``algo.td.start_from``): which finished run each member starts
from, that run's actor weights, and what the member's summary records of them.

``start_from`` names a finished run's folder (every member starts from it) or a population's folder (member
``<seed>`` starts from its ``seed<seed>/``, so a member starts where its solo run would). The folder is read
as every tool reads a run (``engine.evaluation.load_policy``: a finished, intact run whose actor builds);
its actor must have this run's sizes (``network.actor_hidden``, ``network.activation``, the observation it
reads). The weights are written into the members' actors before the loss is built
(``learners.td.learner.start_actors``), so target networks start from them too; critics, temperature and
optimisers start fresh (``algo.td.critic_first_episodes`` fits the critics to the started policy first).
"""

from __future__ import annotations

from pathlib import Path

from engine import rundir
from engine.checkpoint import load_tensors
from engine.config import ConfigError, RunConfig
from engine.outputs import RunFolderError, file_digest


def start_folder(base: Path, seed: int) -> Path:
    """The finished run member ``seed`` starts from: ``base`` itself if it holds a run, else ``base/seed<seed>``."""
    base = Path(base)
    if rundir.state(base).kind == "empty" and (base / f"seed{seed}").is_dir():
        return base / f"seed{seed}"
    return base


def start_actors(cfg: RunConfig, seeds: tuple[int, ...]) -> list[dict] | None:
    """Per member of ``seeds``: {"state": the start's actor weights (a solo actor's names), "gaussian": whether
    they are a Gaussian actor's (loc and scale), "record": what summary.json says of the start}; None without
    ``algo.td.start_from``. ``ConfigError`` in one line when a start cannot be this run's actor."""
    from engine.evaluation import load_policy
    from learners.registry import spec

    td = getattr(cfg.algo, "td", None)
    if td is None or td.start_from is None:
        return None
    if td.observation_norm:
        raise ConfigError("algo.td.start_from with algo.td.observation_norm: the started actor would read "
                          "observations normalised by fresh statistics; start without observation_norm")
    starts = []
    for seed in seeds:
        folder = start_folder(Path(td.start_from), seed)
        try:
            _, settings = load_policy(folder)
        except (RunFolderError, ValueError) as err:
            raise ConfigError(f"algo.td.start_from: {err}") from None
        state = load_tensors(folder / "actor.pt", "actor")
        state = {k.removeprefix("module."): v for k, v in state.items()}  # TorchRL's layout (until da21af2)
        if any(k.startswith("norm.") for k in state):
            raise ConfigError(f"algo.td.start_from: {folder} acted on normalised observations "
                              "(algo.td.observation_norm); its actor cannot start one that reads them as they are")
        ours = (list(cfg.network.actor_hidden), cfg.network.activation, cfg.env.past_steps)
        network, env = settings["network"], settings["env"]
        theirs = (list(network["actor_hidden"]), network["activation"], env.get("past_steps", 0))
        if ours != theirs:
            raise ConfigError(f"algo.td.start_from: {folder}'s actor has hidden layers {theirs[0]}, activation "
                              f"{theirs[1]} and past steps {theirs[2]}; this run's {ours[0]}, {ours[1]} and {ours[2]}")
        loss = settings["algo"]["loss"]
        summary = rundir.state(folder).summary
        starts.append({"state": state, "gaussian": spec(loss).gaussian_actor,
                       "record": {"folder": str(folder.resolve()), "algo": settings["algo"].get("name"),
                                  "seed": summary.get("seed"), "episodes": summary.get("episodes"),
                                  "actor_sha256": file_digest(folder / "actor.pt")["sha256"]}})
    return starts
