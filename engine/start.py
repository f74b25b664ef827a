"""A run whose networks start from others' (``algo.td.start_from``, ``algo.td.start_critics_from``): which
source each member starts from, its weights, and what the member's summary records of them.

``start_from`` names, for each member ``<seed>``:

- a finished run's folder (every member starts from its actor), or a population's folder whose ``seed<seed>/``
  is one (a member starts where its solo run would);
- a folder of ``python -m pupil.search --out`` results, whose ``policy-<seed>.pt`` holds an actor's weights
  (a run's names and shapes), or one such file for every member.

A run is read as every tool reads one (``engine.evaluation.load_policy``: a finished, intact run whose actor
builds); a weights file through the door (``engine.checkpoint.load_tensors``: plain tensors, finite). The
actor must have this run's sizes (``network.actor_hidden``, ``network.activation``, the observation it reads);
the weights are written into the members' actors before the loss is built (``learners.td.learner``), so
target networks start from them too. ``start_critics_from`` names a finished run (or a population's folder)
whose ``critic.pt`` starts the Q-networks and their targets (the same learner's shapes); without it critics,
temperature and optimisers start fresh (``algo.td.critic_first_episodes`` fits the critics to the started
policy first).
"""

from __future__ import annotations

from pathlib import Path

from engine import rundir
from engine.checkpoint import load_tensors
from engine.config import ConfigError, RunConfig
from engine.outputs import RunFolderError, file_digest


def start_source(base: Path, seed: int, option: str = "algo.td.start_from") -> Path:
    """What member ``seed`` starts from: ``base`` if it is a file or holds a finished run, else its
    ``seed<seed>/`` (a population's member) or its ``policy-<seed>.pt`` (a search's result), else ``base``
    (whose reading then says what is wrong); ``ConfigError`` if ``base`` does not exist."""
    base = Path(base)
    if not base.exists():
        raise ConfigError(f"{option}: {base} does not exist: give a finished run's folder, a population's, or a search's "
                          "weights (engine/start.py)")
    if base.is_file() or rundir.state(base).kind == "finished":
        return base
    for candidate in (base / f"seed{seed}", base / f"policy-{seed}.pt"):
        if candidate.exists():
            return candidate
    return base


def _finished_run(folder: Path, option: str) -> dict:
    """The settings of the finished run in ``folder``, read as every tool reads a run."""
    from engine.evaluation import load_policy

    try:
        return load_policy(folder)[1]
    except (RunFolderError, ValueError) as err:
        raise ConfigError(f"{option}: {err}") from None


def _tensors(path: Path, what: str, option: str, network) -> dict:
    import torch

    from engine.evaluation import saved_actor
    from engine.limits import weights_limit

    try:
        state = load_tensors(path, what, limit=weights_limit(network, what))  # this run's shapes bound the file
    except (ValueError, OSError) as err:
        raise ConfigError(f"{option}: {err}") from None
    if not isinstance(state, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                              for k, v in state.items()):
        raise ConfigError(f"{option}: {path} is not an {what}'s weights (a mapping of names to tensors)")
    if not all(torch.isfinite(v).all() for v in state.values()):
        raise ConfigError(f"{option}: {path} holds non-finite weights")
    return saved_actor(state) if what == "actor" else state


def start_actors(cfg: RunConfig, seeds: tuple[int, ...]) -> list[dict] | None:
    """Per member of ``seeds``: {"state": the start's actor weights (a solo actor's names), "critic": its
    Q-networks' (``start_critics_from``) or None, "record": what summary.json says of the start}; None
    without ``algo.td.start_from``. ``ConfigError`` in one line when a start cannot be this run's."""
    td = getattr(cfg.algo, "td", None)
    if td is None or td.start_from is None:
        if td is not None and td.start_critics_from is not None:
            raise ConfigError("algo.td.start_critics_from starts the critics of a started actor; give algo.td.start_from too")
        return None
    option = "algo.td.start_from"
    if td.observation_norm:
        raise ConfigError(f"{option} with algo.td.observation_norm: the started actor would read "
                          "observations normalised by fresh statistics; start without observation_norm")
    ours = (list(cfg.network.actor_hidden), cfg.network.activation, cfg.env.past_steps)
    starts = []
    for seed in seeds:
        source = start_source(Path(td.start_from), seed)
        if source.is_file():  # a search's weights: its shapes are checked where they are written
            record = {"file": str(source.resolve())}
            path = source
        else:
            settings = _finished_run(source, option)
            network, env = settings["network"], settings["env"]
            theirs = (list(network["actor_hidden"]), network["activation"], env.get("past_steps", 0))
            if ours != theirs:
                raise ConfigError(f"{option}: {source}'s actor has hidden layers {theirs[0]}, activation {theirs[1]} "
                                  f"and past steps {theirs[2]}; this run's {ours[0]}, {ours[1]} and {ours[2]}")
            summary = rundir.state(source).summary
            record = {"folder": str(source.resolve()), "algo": settings["algo"].get("name"),
                      "seed": summary.get("seed"), "episodes": summary.get("episodes")}
            path = source / "actor.pt"
        state = _tensors(path, "actor", option, cfg.network)
        if any(k.startswith("norm.") for k in state):
            raise ConfigError(f"{option}: {path} acted on normalised observations (algo.td.observation_norm); "
                              "it cannot start an actor that reads them as they are")
        record["actor_sha256"] = file_digest(path)["sha256"]
        critic = None
        if td.start_critics_from is not None:
            folder = start_source(Path(td.start_critics_from), seed, "algo.td.start_critics_from")
            _finished_run(folder, "algo.td.start_critics_from")
            critic = _tensors(folder / "critic.pt", "critic", "algo.td.start_critics_from", cfg.network)
            record["critics"] = {"folder": str(folder.resolve()),
                                 "critic_sha256": file_digest(folder / "critic.pt")["sha256"]}
        starts.append({"state": state, "critic": critic, "record": record})
    return starts


def check_starts(cfg: RunConfig, out_dir: Path) -> None:
    """Before a run clears or writes anything (``engine.runner``): every member's start can be read and is this
    run's, and none lies in the run's own folder (``overwrite=true`` would clear it first); ``ConfigError``."""
    td = getattr(cfg.algo, "td", None)
    if td is None:
        return
    out = Path(out_dir).resolve()
    for option, value in (("algo.td.start_from", td.start_from), ("algo.td.start_critics_from", td.start_critics_from)):
        for seed in cfg.members if value is not None else ():
            source = start_source(Path(value), seed, option).resolve()
            if source == out or out in source.parents:
                raise ConfigError(f"{option}: {source} is in this run's own folder {out}; a run cannot start from "
                                  "itself: copy the start elsewhere first")
    start_actors(cfg, cfg.members)
