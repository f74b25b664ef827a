"""Training runs, start to finish: ``train_population(cfg, out_dir) -> summaries``.

A run is a population of independent members, one per seed of ``cfg.members`` (a solo run is a
population of one), trained in lockstep in one process. ``_train`` is the science, top to bottom in one
screen: its construction is one call, ``engine.setup.build`` (generators, cars, the learner family's
``build``, the schedule), then the loop; what a run owes its folders besides is
``engine.run_context.RunContext``'s. Per episode
(docs/specification.md's protocol, as ``collectors.replay`` schedules it), for every member at once:

1. if the schedule trains on memory and the memory is not empty: a phase on the memory;
2. collect one episode with the stochastic policy; its total reward is the learning curve;
3. Monte-Carlo returns; the episode's transitions join the replay memory;
4. if the schedule trains on recent experience: a phase on this episode's transitions.

Each member writes the folder a solo run writes (metrics.csv, summary.json, actor.pt,
critic.pt): ``out_dir`` itself for a solo run, ``out_dir/seed<seed>/`` in a population
(``cfg.seeds``). A member that diverges is frozen and recorded; the others go on. The
population's checkpoint (``out_dir/checkpoint.pt``) holds every member.

With ``cfg.processes`` > 1 the members are split into that many parts, each trained as a
population of its own in a process of its own (each with its checkpoint,
``out_dir/checkpoint-<first seed>.pt``): since every member computes what its solo run does,
the results are the same files, on more cores.
"""

from __future__ import annotations

import dataclasses
import signal
import time
import warnings
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path


from collectors import add_monte_carlo_returns, n_step_transitions
from engine import checkpoint, numerics, setup
from engine import rundir
from door import files
from engine.processes import (RunStopped, StopSignals, descendants, exit_with_parent, keep_freed_memory,
                              spawn_context, stop_at_once)
from engine.config import ConfigError, RunConfig, settings_difference
from engine.outputs import METRICS_FILE, kept_rows
from engine.start import check_starts
from engine.run_context import (NUMERICS_KEYS, RunContext, same_numerics, member_folder,  # noqa: F401 (member_folder: this
                                numerics_segment)                                       # module's interface too)
from learners import compiling
from learners.base import MetricTotals


def run_settings(settings: dict) -> dict:
    """The part of a config mapping that decides what a run computes (``RunConfig.run_settings``)."""
    return RunConfig.run_settings(settings)


def finished_run(folder: Path, settings: dict | None, overwrite: bool = False, solo: bool = True) -> dict | None:
    """The summary of a finished run of these settings in ``folder``, if there is one; otherwise
    the folder is made ready for a new run (``engine.rundir``'s rule).

    A finished run of other settings, a damaged folder, or (for a population's member,
    ``solo=False``) a solo run's checkpoint raises ``ConfigError`` (their results would be lost),
    unless ``overwrite``: then the folder is cleared, its summary first. An empty folder is
    started afresh."""
    found = rundir.state(folder)
    if found.kind == "finished" and RunConfig.same_run(found.summary.get("settings"), settings):
        return found.summary
    problem = rundir.refusal(found, settings, solo)
    if problem is None:  # empty, or a solo run's own checkpoint (which _resumed_parts continues)
        return None
    if not overwrite:
        raise ConfigError(problem)
    rundir.clear(folder)
    return None


def train(cfg: RunConfig, out_dir: Path, settings: dict | None = None) -> dict:
    """Train a solo run (``cfg.seeds`` unset) into ``out_dir``; returns its summary."""
    if cfg.seeds is not None and len(cfg.seeds) != 1:
        raise ValueError("train() runs one seed; use train_population() for several")
    return train_population(cfg, out_dir, settings)[0]


def train_population(cfg: RunConfig, out_dir: Path, settings: dict | None = None,
                     skipped: list | None = None, on_start=None, stop_file: Path | None = None,
                     root: Path | None = None) -> list[dict]:
    """Train one run per seed of ``cfg.members`` together; returns their summaries (in that order).

    ``settings`` (the config as a plain mapping) is stored in each summary.json (as the
    member's solo settings) and in the checkpoint, to recognise runs later. Members whose folder
    holds a finished run of the same settings are not trained again (their summaries are
    returned, and (folder, summary) appended to ``skipped`` if given). If ``out_dir`` holds a checkpoint
    of the same settings, the population continues from it exactly as if it had never stopped.

    The run holds its folders' locks (``engine.rundir.lock``) throughout; every refusal (another
    process on the folder, a damaged folder, a finished run or checkpoint of other settings) comes
    before anything is written, and ``on_start()`` (if given) is called once the run is sure to
    train. Every folder from ``root`` (a sweep's folder; default ``out_dir``) down to each member's is
    a real folder, never a link (``door.files.folder``), checked before anything is written.
    SIGINT or SIGTERM stops it at the end of the episode with a checkpoint (``RunStopped``),
    as does ``stop_file`` appearing (a sweep's, ``engine.processes.STOP_FILE``); a population split
    over processes passes the stop on to every part, and ends when they all have.
    """
    numerics.apply(cfg.numerics, cfg.threads)  # torch has loaded: a check that it runs the mode asked for
    keep_freed_memory()  # reuse freed tensors' memory (speed only)
    cfg, compiled = _compile_mode(cfg)
    out_dir = Path(out_dir)
    folders = [out_dir, *(member_folder(cfg, out_dir, s) for s in cfg.members)]
    with rundir.lock(folders, root=out_dir if root is None else root), StopSignals(stop_file=stop_file) as stop:  # refused at once if a folder is in use
        return _train_locked(cfg, out_dir, folders, settings, skipped, on_start, compiled, stop)


def _train_locked(cfg: RunConfig, out_dir: Path, folders: list[Path], settings: dict | None, skipped: list | None,
                  on_start, compiled: dict, stop: StopSignals) -> list[dict]:
    start = time.perf_counter()
    settings = run_settings(settings) if settings is not None else None
    member_settings = {s: cfg.member_settings(settings, s) if settings is not None else None for s in cfg.members}

    for folder in folders:  # links where run files go: refused, even with overwrite (never followed)
        problem = rundir.linked_file(folder)
        if problem:
            raise rundir.RunFolderError(f"{folder} cannot be used: {problem}")
    if cfg.overwrite:  # start afresh: no checkpoint is continued
        check_starts(cfg, out_dir)  # a start that cannot be read (or lies in this folder) refuses before anything is cleared
        for path in checkpoint.in_folder(out_dir):
            files.remove(path)
    for folder in folders:
        rundir.remove_temporaries(folder)  # a killed writer's; never a finished file
    parts = _resumed_parts(out_dir, settings, cfg.resume_numerics)  # each continues as the population it was
    resumed = {seed for _, seeds, _ in parts for seed in seeds}
    for seed in sorted(resumed):  # a checkpoint beside a damaged summary (or a link) is not resumed over
        found = rundir.state(member_folder(cfg, out_dir, seed))
        if found.kind == "damaged":
            raise ConfigError(found.refusal())
    for _, _, payload in parts:  # the rows each checkpoint counts are those it recorded (before anything is written)
        for state in payload["member_states"]:
            kept_rows(member_folder(cfg, out_dir, state["seed"]) / METRICS_FILE, len(state["rewards"]),
                      state.get("metrics"))
    done: dict[int, dict] = {}
    for seed in cfg.members:
        if seed in resumed:
            continue
        folder = member_folder(cfg, out_dir, seed)
        summary = finished_run(folder, member_settings[seed], cfg.overwrite, solo=folder == out_dir)
        if summary is not None:
            done[seed] = summary
            if skipped is not None:
                skipped.append((folder, summary))
    fresh = tuple(s for s in cfg.members if s not in done and s not in resumed)
    chunks = split_members(fresh, max(1, cfg.processes - len(parts)), at_least=2 if compiled["enabled"] else 1)
    for chunk in chunks:
        name = checkpoint.CHECKPOINT_FILE if not parts and len(chunks) == 1 else f"checkpoint-{chunk[0]}.pt"
        parts.append((out_dir / name, chunk, None))
    if not parts:  # every member had finished
        summaries = []
    elif len(parts) == 1:  # on_start once its output files are open (a file they cannot be is refused before it)
        path, seeds, payload = parts[0]
        summaries = _train(cfg, out_dir, seeds, member_settings, settings, payload, path, start, compiled, stop,
                           on_start)
    else:  # one process per part, ``cfg.processes`` at a time
        if on_start is not None:
            on_start()
        summaries = _train_parts(cfg, out_dir, parts, member_settings, settings, compiled, stop)
    for summary in summaries:
        done[summary["seed"]] = summary
    return [done[s] for s in cfg.members]


def _train_parts(cfg: RunConfig, out_dir: Path, parts: list, member_settings: dict, settings: dict | None,
                 compiled: dict, stop: StopSignals) -> list[dict]:
    """Each part in a process of its own, ``cfg.processes`` at a time (spawned: torch does not survive
    fork with threads running). A stop asked of this process, or of any part (a signal sent to it
    alone), is passed on to every part; each saves its checkpoint at its episode's end, parts not yet
    started do not start, and ``RunStopped`` then says where each was saved."""
    context = spawn_context()
    shared = context.Value("i", 0, lock=False)  # the number of the signal that stopped the population (0: none)
    stopped: list[str] = []
    results: dict[int, list[dict]] = {}
    ignored = signal.getsignal(signal.SIGINT) is signal.SIG_IGN  # e.g. a background job's: stays so in the parts
    # The parts start with SIGINT ignored (inherited across their exec) until their initializer sets it as this
    # process has it: a Ctrl-C to the terminal's process group while they import torch is this process's to pass
    # on, not a traceback in each of them
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        pool = ProcessPoolExecutor(min(cfg.processes, len(parts)), mp_context=context, initializer=_part_initializer,
                                   initargs=(shared, ignored))
        futures = {pool.submit(_train_part, cfg, out_dir, seeds, member_settings, settings, path, compiled): i
                   for i, (path, seeds, _) in enumerate(parts)}
    finally:
        signal.signal(signal.SIGINT, previous)
    with pool:
        pending = set(futures)
        try:
            while pending:
                done, pending = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
                for future in done:
                    error = future.exception()
                    if isinstance(error, RunStopped):
                        stopped.append(str(error))
                        if not shared.value:  # a part stopped by a signal of its own: the others follow
                            shared.value = _signal_number(str(error))
                    elif isinstance(error, BrokenProcessPool) and (shared.value or stop.requested):
                        pass  # a part ended by the stop while it was starting: it had saved nothing
                    elif error is not None:
                        shared.value = shared.value or signal.SIGTERM  # the others stop, the error is raised
                        wait(pending)
                        raise error
                    else:
                        results[futures[future]] = future.result()
                if stop.requested is not None and not shared.value:
                    shared.value = signal.Signals[stop.requested].value
        except KeyboardInterrupt:  # a second signal to this process: every part stops at once
            stop_at_once(descendants())
            wait(pending)
            for future in pending:
                if isinstance(future.exception(), RunStopped):
                    stopped.append(str(future.exception()))
        if stopped or shared.value or stop.requested or len(results) < len(parts):
            name = signal.Signals(shared.value).name if shared.value else stop.requested or "SIGINT"
            raise RunStopped(_parts_stopped(name, stopped))
    return [summary for i in sorted(results) for summary in results[i]]


def _signal_number(message: str) -> int:
    return signal.SIGINT if "SIGINT" in message else signal.SIGTERM


def _parts_stopped(name: str, lines: list[str]) -> str:
    """One line for a split population's stop: where each part saved."""
    import re

    saved = [re.search(r"saved at episode (\d+) \((.*)\)", line) for line in lines]
    where = sorted(f"{Path(m.group(2)).name} at episode {m.group(1)}" for m in saved if m)
    if not where:
        return f"Stopped by {name} before any part saved a checkpoint: the same command starts the run afresh"
    folder = Path(next(m for m in saved if m).group(2)).parent
    unsaved = len(lines) - len(where)
    return (f"Stopped by {name}; saved {', '.join(where)} in {folder}"
            f"{f' ({unsaved} part(s) had saved nothing yet)' if unsaved else ''}: the same command resumes from there")


def _part_initializer(shared, sigint_ignored: bool = False) -> None:
    """A part's process, once started: the population's stop, and SIGINT as the parent had it."""
    global _SHARED_STOP
    _SHARED_STOP = shared
    signal.signal(signal.SIGINT, signal.SIG_IGN if sigint_ignored else signal.default_int_handler)


_SHARED_STOP = None  # in a part's process: the population's stop (``_train_parts``)


def split_members(seeds: tuple[int, ...], parts: int, at_least: int = 1) -> list[tuple[int, ...]]:
    """``seeds`` in at most ``parts`` consecutive parts of near-equal size, each of at least
    ``at_least`` members (unless there are fewer seeds); no part if no seeds."""
    count = max(1, min(parts, len(seeds) // at_least))
    if not seeds:
        return []
    size, extra = divmod(len(seeds), count)
    bounds = [0]
    for i in range(count):
        bounds.append(bounds[-1] + size + (i < extra))
    return [tuple(seeds[a:b]) for a, b in zip(bounds, bounds[1:])]


def _resumed_parts(out_dir: Path, settings: dict | None,
                   resume_numerics: str = "same") -> list[tuple[Path, tuple[int, ...], dict]]:
    """The checkpoints in ``out_dir`` (``checkpoint.pt``, or one per part of a split population):
    (path, members, payload) each; ``ConfigError`` if one is of other settings, or (unless
    ``resume_numerics="any"``) was computed with other products than this process computes with."""
    parts = []
    now = numerics_segment(0)
    for path in checkpoint.in_folder(out_dir):
        payload = checkpoint.load(path)
        old, new = RunConfig.training_settings(payload.get("settings")), RunConfig.training_settings(settings)
        if not RunConfig.same_run(old, new):
            raise ConfigError(f"the run folder holds a checkpoint of a different configuration ({path.name}: "
                              f"{settings_difference(old, new)}); choose another folder (hydra.run.dir=...) or pass "
                              "overwrite=true to start afresh")
        segments = payload.get("numerics") or []
        if segments and not same_numerics(segments[-1], now) and resume_numerics != "any":
            before, here = (", ".join(f"{k} {seg.get(k)}" for k in NUMERICS_KEYS) for seg in (segments[-1], now))
            why = f" ({now['fallback']})" if "fallback" in now else ""
            raise ConfigError(f"{path} was computed with other numerics ({before}) than this process computes with "
                              f"({here}{why}); continuing would make one run of two, whose numbers no uninterrupted "
                              "run gives. Remove the cause and run the same command again, or pass "
                              "resume_numerics=any to continue (summary.json then records both)")
        members = tuple(payload["members"])
        named = path.name.removeprefix("checkpoint-").removesuffix(".pt")
        if path.name != checkpoint.CHECKPOINT_FILE and named != str(members[0] if members else None):
            raise ConfigError(f"{path} holds the members {list(members)}, not a part starting at seed {named} as its "
                              "name says: renamed or copied; move it away (or pass overwrite=true) to start afresh")
        taken = [seed for _, earlier, _ in parts for seed in earlier if seed in members]
        if taken:
            raise ConfigError(f"{path} holds members {taken} that another checkpoint in {out_dir} holds too: two "
                              "processes would train them into one folder; move one away (or pass overwrite=true)")
        parts.append((path, members, payload))
    return parts


def _train_part(cfg: RunConfig, out_dir: Path, seeds: tuple[int, ...], member_settings: dict,
                settings: dict | None, path: Path, compiled: dict) -> list[dict]:
    """One part of a split population, in a process of its own (it inherits the parent's numerics
    variables, so torch loaded with the same kernels); it ends if the parent dies."""
    exit_with_parent()
    numerics.apply(cfg.numerics, cfg.threads)
    keep_freed_memory()
    start = time.perf_counter()
    payload = checkpoint.load(path) if path.exists() else None
    with StopSignals(shared=_SHARED_STOP) as stop:
        if stop.requested is not None:  # the population was stopped before this part began
            raise RunStopped(f"Stopped by {stop.requested} before part {seeds[0]} started; "
                             f"not started: the same command starts it")
        return _train(cfg, out_dir, seeds, member_settings, settings, payload, path, start, compiled, stop)


def _compile_mode(cfg: RunConfig) -> tuple[RunConfig, dict]:
    """``cfg`` as it will run, and the summary's record of ``compile``: asked for, in effect, and why not.

    Without a C++ compiler (or off Linux x86-64) a run asked to compile warns once and runs eagerly."""
    record = {"requested": cfg.compile, "enabled": False, "reason": None}
    if not cfg.compile:
        return cfg, record
    reason = compiling.unavailable_reason(cfg.device)
    if reason is None:
        try:
            cache = compiling.inductor_cache()
        except RuntimeError as err:
            reason = str(err)
    if reason is not None:
        warnings.warn(f"compile=true: running eagerly instead, because {reason}", stacklevel=2)
        return dataclasses.replace(cfg, compile=False), {**record, "reason": reason}
    return cfg, {**record, "enabled": True, "cache": cache}


def _train(cfg: RunConfig, out_dir: Path, seeds: tuple[int, ...], member_settings: dict, settings: dict | None,
           payload: dict | None, checkpoint_path: Path, start: float, compiled: dict,
           stop: StopSignals, on_start=None) -> list[dict]:
    """One population's run, top to bottom, in the shape of TorchRL's sota scripts: the environment, the
    learner (networks, loss, optimisers, replay memory) and the schedule (``setup.build``), the collector;
    then per episode an update on the memory, an episode collected and stored, an update on it, its rows
    logged. What a run owes its folders besides (resume, checkpoints, records, summaries) is the
    ``RunContext``'s, entered at five points."""
    context = RunContext(cfg, out_dir, seeds, member_settings, settings, checkpoint_path, start, compiled, stop)
    run = setup.build(cfg, seeds)
    env, learner, schedule, minibatch = run.env, run.learner, run.schedule, run.minibatch_size
    memory, phases = learner.memory, learner.phases
    first = context.resume(run, payload)  # a checkpoint's state, exactly
    collector = setup.make_episode_collector(cfg, env, learner.sampler, episodes=cfg.episodes - first)
    with context.training(collector, on_start):
        episodes = iter(collector)
        for episode in range(first, cfg.episodes):
            if not context.running:
                break
            totals = MetricTotals()
            with context.timed("train_s"):
                if schedule.train_on_memory and len(memory):
                    context.freeze(phases.run(memory.contents(), minibatch, totals, episode), episode)
            with context.timed("rollout_s"):
                batch = next(episodes)
                if learner.monte_carlo:
                    add_monte_carlo_returns(batch, cfg.gamma)
                recent = batch.select(*learner.transition_keys)  # [members, steps]
                if learner.n_step > 1:
                    recent = n_step_transitions(recent, cfg.gamma, learner.n_step)
                memory.add(recent)
            with context.timed("train_s"):
                if schedule.train_on_recent:
                    context.freeze(phases.run(recent.clone(), minibatch, totals, episode), episode)
            context.log(episode, batch, totals)  # metrics.csv, progress; a checkpoint when due or stopping
    return context.finish()  # weights and summaries
