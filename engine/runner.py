"""Training runs, start to finish: ``train_population(cfg, out_dir) -> summaries``.

A run is a population of independent members, one per seed of ``cfg.members`` (a solo run is a
population of one), trained in lockstep in one process. Its construction is one call, ``engine.setup.build``
(generators, cars, the learner family's ``build``, the schedule); the loop below only runs it. Per episode
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
import math
import signal
import sys
import time
import warnings
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tensordict import TensorDictBase

from collectors import add_monte_carlo_returns, n_step_transitions
from engine import checkpoint, numerics, setup
from engine import rundir
from door import files
from engine.processes import (RunStopped, StopSignals, descendants, exit_with_parent, keep_freed_memory,
                              spawn_context, stop_at_once)
from engine.config import ConfigError, RunConfig, settings_difference
from engine.outputs import METRICS_FILE, MetricsWriter, file_record, kept_rows, metric_columns, write_summary
from engine.progress import Progress
from engine.version import code_version, software_versions
from learners import compiling
from learners.base import MetricTotals


def run_settings(settings: dict) -> dict:
    """The part of a config mapping that decides what a run computes (``RunConfig.run_settings``)."""
    return RunConfig.run_settings(settings)


def member_folder(cfg: RunConfig, out_dir: Path, seed: int) -> Path:
    """Where member ``seed`` writes: ``out_dir`` for a solo run, ``out_dir/seed<seed>`` in a population."""
    return Path(out_dir) if cfg.seeds is None else Path(out_dir) / f"seed{seed}"


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


@dataclass
class Member:
    """One run of the population: its seed, folder and results so far."""

    seed: int
    folder: Path
    settings: dict | None
    rewards: list[float] = field(default_factory=list)
    status: str = "running"  # then "completed" or "diverged"
    failure: dict | None = None
    metrics: MetricsWriter | None = None
    rows: dict | None = None  # size and SHA-256 of metrics.csv as the last checkpoint counted it

    def state(self) -> dict:
        return {"seed": self.seed, "rewards": list(self.rewards), "status": self.status, "failure": self.failure,
                "metrics": self.metrics.record() if self.metrics is not None else None}


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


NUMERICS_KEYS = ("mode", "kernels", "mkl_branch", "products")  # what decides a run's bits (numerics.in_effect)


def numerics_segment(first_episode: int) -> dict:
    """The products this process computes with, from episode ``first_episode`` on (a checkpoint
    keeps one per session that computed differently; the summary reports them all)."""
    effect = numerics.in_effect()
    return {"from_episode": first_episode, **{key: effect.get(key) for key in NUMERICS_KEYS},
            **({"fallback": effect["fallback"]} if "fallback" in effect else {})}


def _same_numerics(a: dict, b: dict) -> bool:
    """Whether two sessions compute the same bits: the same mode, torch kernels, MKL branch and
    products (the project's kernels on any instruction set count as one: ``fma-avx512``,
    ``fma-avx2`` and ``fma-scalar`` give the same bits, tested)."""
    def key(segment: dict) -> tuple:
        products = str(segment.get("products"))
        return (segment.get("mode"), segment.get("kernels"), segment.get("mkl_branch"),
                "fma" if products.startswith("fma-") else products)

    return key(a) == key(b)


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
        if segments and not _same_numerics(segments[-1], now) and resume_numerics != "any":
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
    if compiled["enabled"]:
        compiling.configure(cfg.numerics)  # from a clean slate, so a run compiles the same in any process
    compile_start = compiling.seconds_spent() if compiled["enabled"] else 0.0
    run = setup.build(cfg, seeds)
    env, generators, learner, schedule, minibatch = run.env, run.generators, run.learner, run.schedule, run.minibatch_size
    memory, phases = learner.memory, learner.phases
    members = [Member(s, member_folder(cfg, out_dir, s), member_settings[s]) for s in seeds]
    for member in members:
        files.folder(member.folder, out_dir, create=True)

    parts = learner.state_parts()
    first, timing = 0, {"rollout_s": 0.0, "train_s": 0.0}
    cpu_start = time.process_time()  # this process's CPU time (every thread): the run's compute
    earlier_wall: float | None = 0.0  # wall time of the sessions before a resume (None: not recorded)
    earlier_cpu: float | None = 0.0  # CPU time of the sessions before a resume (None: not recorded)
    code = dict(code_version())
    segments = [numerics_segment(0)]  # the products each session computed with (a new one where they differ)
    paths = [{"from_episode": 0, "collector": cfg.env.collector, **phases.path}]  # what ran (a new one where it differs)
    if phases.code_refusal:
        print(f"Note: the fused update steps are off because {phases.code_refusal}: the loss module computes this "
              "run's updates, at its own speed (summary.json's paths records it)", file=sys.stderr)
    if payload is not None:
        first, timing = _restore(payload, parts, env, generators, phases, members)
        earlier_paths = [dict(path) for path in payload.get("paths") or []]
        if earlier_paths and {k: v for k, v in earlier_paths[-1].items() if k != "from_episode"} == \
                {k: v for k, v in paths[0].items() if k != "from_episode"}:
            paths = earlier_paths
        else:
            paths = [*earlier_paths, {**paths[0], "from_episode": first}]
        # a checkpoint from before the record: its products are unknown, so this session's are a segment of their own
        segments = [dict(seg) for seg in payload.get("numerics") or []] or [{"from_episode": 0, "recorded": False}]
        now = numerics_segment(first)
        if not _same_numerics(segments[-1], now):
            segments.append(now)
        earlier_wall = timing.pop("wall_s", None)
        earlier_cpu = timing.pop("cpu_s", None)
        earlier = payload.get("code") or {"source": None}
        if earlier.get("source") != code["source"]:  # this run mixes two versions of the code
            code["resumed_from"] = {k: v for k, v in earlier.items() if k != "resumed_from"}
        elif earlier.get("resumed_from"):
            code["resumed_from"] = earlier["resumed_from"]
    earlier_compile = timing.pop("compile_s", 0.0)

    def compile_time() -> dict:  # seconds spent compiling, every session of a resumed run included
        if not compiled["enabled"]:
            return {}
        return {"compile_s": earlier_compile + compiling.seconds_spent() - compile_start}

    collector = setup.make_episode_collector(cfg, env, learner.sampler, episodes=cfg.episodes - first)
    columns = metric_columns(phases)
    for member in members:
        member.metrics = MetricsWriter(member.folder, columns, cfg.logger, keep_rows=len(member.rewards),
                                       expect=member.rows)
    if on_start is not None:
        on_start()

    progress = _progress(cfg, seeds, initial=first)
    episodes = iter(collector)
    saved = first if payload is not None else None  # the episode the last checkpoint holds
    try:
        for episode in range(first, cfg.episodes):
            if not any(m.status == "running" for m in members):
                break
            totals = MetricTotals()
            with _timer(timing, "train_s"):
                if schedule.train_on_memory and len(memory):
                    _freeze(phases.run(memory.contents(), minibatch, totals, episode), episode, members, phases)
            with _timer(timing, "rollout_s"):
                batch = next(episodes)
                if learner.monte_carlo:
                    add_monte_carlo_returns(batch, cfg.gamma)
                recent = batch.select(*learner.transition_keys)  # [members, steps]
                if learner.n_step > 1:
                    recent = n_step_transitions(recent, cfg.gamma, learner.n_step)
                memory.add(recent)
            with _timer(timing, "train_s"):
                if schedule.train_on_recent:
                    _freeze(phases.run(recent.clone(), minibatch, totals, episode), episode, members, phases)
            diagnostics = totals.means(len(members))
            for r, member in enumerate(members):
                if member.status == "running":
                    row = {**_episode_results(episode, batch, r), **diagnostics[r]}
                    member.metrics.write(row)
                    member.rewards.append(row["total_reward"])
            _show(progress, members)
            done = episode + 1
            stopping = stop.requested is not None and done < cfg.episodes
            if cfg.checkpoint_every and done < cfg.episodes and (done % cfg.checkpoint_every == 0 or stopping):
                so_far = {**({} if earlier_wall is None else {"wall_s": earlier_wall + time.perf_counter() - start}),
                          **({} if earlier_cpu is None else {"cpu_s": earlier_cpu + time.process_time() - cpu_start})}
                checkpoint.save(checkpoint_path, _payload(done, {**timing, **so_far, **compile_time()}, settings,
                                                          parts, env, code, segments, paths,
                                                          generators, phases, members, learner.sampler))
                saved = done
            if stopping:
                raise RunStopped(_stopped(stop.requested, done, cfg.episodes, saved, checkpoint_path))
    except KeyboardInterrupt as err:  # a second signal (or Ctrl-C outside StopSignals): at once
        if isinstance(err, RunStopped):
            raise
        raise RunStopped(_stopped(stop.requested or "SIGINT", None, cfg.episodes, saved, checkpoint_path)) from None
    finally:
        progress.close()
        for member in members:
            if member.metrics is not None:
                member.metrics.close()
        collector.shutdown()

    summaries = []
    session = round(time.perf_counter() - start, 3)
    # wall_time_s and cpu_time_s cover every session of a resumed run (None if its checkpoint did not
    # record them); both are the process's, for all the members it trained (population.size)
    wall = round(session + earlier_wall, 3) if earlier_wall is not None else None
    cpu = round(time.process_time() - cpu_start + earlier_cpu, 3) if earlier_cpu is not None else None
    session_wall = {"wall_time_session_s": session} if first else {}
    for r, member in enumerate(members):
        if member.status == "running":
            member.status = "completed"
        weights = learner.member_weights(r) if member.status == "completed" else {}
        for name in ("actor", "critic"):
            path = member.folder / f"{name}.pt"
            if member.status == "completed":  # the paper's: in the solo networks' layout (learners.solo)
                checkpoint.save_tensors(path, weights[name])
            else:  # non-finite weights are of no use; no stale file from an earlier run either
                files.remove(path)
        window = member.rewards[-cfg.final_window:]
        evaluation = (_evaluate(cfg, member.seed, weights)
                      if cfg.eval_seeds is not None and member.status == "completed" else None)
        summary = {
            "algo": cfg.algo.name, "er": cfg.er.name, "seed": member.seed,
            "episodes": len(member.rewards), "episodes_planned": cfg.episodes,
            "final_mean": _mean(window) if window else None, "final_window": len(window),
            "status": member.status, "diverged": member.failure,
            "wall_time_s": wall, **session_wall, "cpu_time_s": cpu,
            "resumed_at": first or None,
            **{f"time/{key}": round(value, 3) for key, value in {**timing, **compile_time()}.items()},
            "population": {"seeds": list(seeds), "size": len(seeds)},
            **({"evaluation": evaluation} if evaluation is not None else {}),
            **({"track_file": env.sim.file_track.reading.record()} if env.sim.file_track is not None else {}),
            "code": code, "software": software_versions(), "numerics": _numerics_record(segments),
            "compile": compiled, "paths": paths, "settings": member.settings,
            "files": file_record(member.folder, rundir.RECORDED_FILES),  # what this summary stands for
        }
        summaries.append(write_summary(member.folder, summary))
    files.remove(checkpoint_path)  # the runs are finished: summaries and weights remain
    return summaries


def _numerics_record(segments: list[dict]) -> dict:
    """summary.json's "numerics": what this process ran (``numerics.in_effect()``) when every session
    computed with the same products; otherwise mode ``mixed``, and each session's products from the
    episode it began with (a run never reports one mode for numbers made with two)."""
    effect = numerics.in_effect()
    if len(segments) <= 1:
        return effect
    return {"mode": "mixed", "kernels": effect.get("kernels"), "segments": segments}


def _evaluate(cfg: RunConfig, seed: int, weights: dict) -> dict:
    """The final deterministic policy's mean total reward on its own track and on ``cfg.eval_seeds`` (``weights``:
    the member's {"actor": ..., "critic": ...})."""
    from engine.evaluation import evaluate, make_policy, own_track
    from racing.config import RacingConfig

    network = {"actor_hidden": list(cfg.network.actor_hidden), "activation": cfg.network.activation}
    policy = make_policy(cfg.algo.loss, network, RacingConfig(**cfg.env.options).obs_size, weights["actor"],
                         cfg.env.past_steps, algo=cfg.algo, critic=weights["critic"], gamma=cfg.gamma)
    settings = {"env": {"options": dict(cfg.env.options), "nearest_ray": cfg.env.nearest_ray}}
    settings["env"].update(track=cfg.env.track, track_file=cfg.env.track_file, track_scale=cfg.env.track_scale,
                           track_closed=cfg.env.track_closed)
    track = own_track({"env": settings["env"], "seed": seed})
    own = evaluate(policy, settings, [track], cfg.eval_episodes)[track]
    others = evaluate(policy, settings, list(cfg.eval_seeds), cfg.eval_episodes)
    return {"episodes": cfg.eval_episodes, "own_track": own, "tracks": {str(k): v for k, v in others.items()},
            "mean": _mean(list(others.values()))}


def _freeze(failed: dict[int, str], episode: int, members: list[Member], phases) -> None:
    """Record and freeze the members that diverged in the last phase."""
    for r, reason in sorted(failed.items()):
        members[r].status, members[r].failure = "diverged", {"episode": episode, "reason": reason}
        phases.freeze(r)


def _payload(episodes_done: int, timing: dict, settings: dict | None, parts: dict, env, code: dict, segments: list,
             paths: list, generators: list[torch.Generator], phases, members: list[Member], sampler) -> dict:
    if not sampler.at_block_boundary:
        raise RuntimeError("a checkpoint must be taken between episodes")
    return {
        "settings": settings, "code": code, "numerics": segments, "paths": paths, "episodes_done": episodes_done,
        "timing": dict(timing),
        "members": [m.seed for m in members], "member_states": [m.state() for m in members],
        **{name: part.state_dict() for name, part in parts.items()},
        "generators": [g.get_state() for g in generators], "active": phases.active.clone(),
        "rng": checkpoint.capture_rng(), "sim": checkpoint.arrays_to_tensors(env.sim_state()),
    }


def _restore(payload: dict, parts: dict, env, generators: list[torch.Generator], phases,
             members: list[Member]) -> tuple[int, dict]:
    try:
        for name, part in parts.items():
            part.load_state_dict(payload[name])
        env.load_sim_state(checkpoint.arrays_from_tensors(payload["sim"]))
        for generator, state in zip(generators, payload["generators"], strict=True):
            generator.set_state(state)
        phases.active.copy_(payload["active"])
        for member, state in zip(members, payload["member_states"], strict=True):
            if state["seed"] != member.seed:
                raise ValueError(f"member {member.seed} found {state['seed']}")
            member.rewards, member.status, member.failure = list(state["rewards"]), state["status"], state["failure"]
            member.rows = state.get("metrics")  # None in checkpoints from before rows were recorded
        checkpoint.restore_rng(payload["rng"])
        return int(payload["episodes_done"]), dict(payload["timing"])
    except (KeyError, RuntimeError, ValueError, TypeError) as err:
        raise checkpoint.CheckpointError(f"the checkpoint does not fit this run ({type(err).__name__}: "
                                         f"{str(err).splitlines()[0][:200]}); delete it to start afresh") from None


def _episode_results(episode: int, batch: TensorDictBase, member: int) -> dict:
    """Learning-curve values of one member's episode (the batch is [members, steps])."""
    keys = batch.keys(True)
    return {
        "episode": episode,
        "total_reward": float(batch["next", "reward"][member].sum(dtype=torch.float64)),
        "crashes": int(batch["next", "crashed"][member].sum()) if ("next", "crashed") in keys else None,
        "final_checkpoint": int(batch["next", "checkpoint"][member, -1].sum()) if ("next", "checkpoint") in keys
        else None,
    }


def _stopped(signal_name: str, done: int | None, planned: int, saved: int | None, path: Path) -> str:
    """The one line a stopped run ends with."""
    where = f"after episode {done} of {planned}" if done is not None else f"during an episode (of {planned})"
    if saved is None:
        return (f"Stopped by {signal_name} {where}; no checkpoint was saved (checkpoint_every=0 or none yet): "
                "the same command starts the run afresh")
    return (f"Stopped by {signal_name} {where}; saved at episode {saved} ({path}): the same command resumes "
            "from there")


def _mean(values: list[float]) -> float:
    return math.fsum(values) / len(values)


class _timer:
    def __init__(self, totals: dict, key: str):
        self.totals, self.key = totals, key

    def __enter__(self):
        self.start = time.perf_counter()

    def __exit__(self, *exc):
        self.totals[self.key] += time.perf_counter() - self.start


def _progress(cfg: RunConfig, seeds: tuple[int, ...], initial: int = 0) -> Progress:
    who = f"seed{seeds[0]}" if len(seeds) == 1 else f"{len(seeds)} seeds"
    return Progress(f"{cfg.algo.name}/{cfg.er.name}/{who}", cfg.episodes, initial=initial, enabled=cfg.progress)


def _show(progress: Progress, members: list[Member]) -> None:
    running = [m for m in members if m.status == "running" and m.rewards]
    diverged = sum(m.status == "diverged" for m in members) or None
    if not running:
        progress.update(diverged=diverged)
        return
    last = _mean([m.rewards[-1] for m in running])
    last20 = _mean([_mean(m.rewards[-20:]) for m in running])
    progress.update(reward=last, last20=last20, diverged=diverged)
