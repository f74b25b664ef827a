"""What a run is besides its science: ``RunContext``, the one narrow interface the training loop
(``engine.runner._train``) enters.

The loop reads as the science it runs: build, collect, store, update, log. Everything else a run owes
its folders lives here, in the order the loop meets it:

- ``RunContext(...)``: the compile settings and the session's clocks;
- ``resume(run, payload)``: each member's folder, the records a summary carries (the code version, the
  products each session computed with, what computed the updates and why, time), a checkpoint's state
  restored exactly, and the one-line note when the fused update steps step aside for an edited loss;
- ``training(collector, on_start)``: the members' metrics files and the progress line opened, a second
  signal turned into a clean stop, everything closed however the loop ends;
- ``timed(key)``, ``freeze(failed, episode)``, ``log(episode, batch, totals)``: the loop's time, its
  diverged members, and after each episode its rows, progress, and a checkpoint when one is due or a
  stop was asked for (``RunStopped`` then says where it was saved);
- ``finish()``: the weights and the sealed summaries, the checkpoint removed.
"""

from __future__ import annotations

import contextlib
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tensordict import TensorDictBase

from door import files
from engine import checkpoint, numerics, rundir
from engine.config import ConfigError, RunConfig
from engine.outputs import MetricsWriter, file_record, metric_columns, write_summary
from engine.processes import RunStopped, StopSignals
from engine.progress import Progress
from engine.version import code_version, software_versions
from learners import compiling
from learners.base import MetricTotals


def member_folder(cfg: RunConfig, out_dir: Path, seed: int) -> Path:
    """Where member ``seed`` writes: ``out_dir`` for a solo run, ``out_dir/seed<seed>`` in a population."""
    return Path(out_dir) if cfg.seeds is None else Path(out_dir) / f"seed{seed}"


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


DETERMINISTIC_COLUMN = "deterministic"  # metrics.csv: eval_every's score of the deterministic policy
NUMERICS_KEYS = ("mode", "kernels", "mkl_branch", "products")  # what decides a run's bits (numerics.in_effect)


def numerics_segment(first_episode: int) -> dict:
    """The products this process computes with, from episode ``first_episode`` on (a checkpoint
    keeps one per session that computed differently; the summary reports them all)."""
    effect = numerics.in_effect()
    return {"from_episode": first_episode, **{key: effect.get(key) for key in NUMERICS_KEYS},
            **({"fallback": effect["fallback"]} if "fallback" in effect else {})}


def same_numerics(a: dict, b: dict) -> bool:
    """Whether two sessions compute the same bits: the same mode, torch kernels, MKL branch and
    products (the project's kernels on any instruction set count as one: ``fma-avx512``,
    ``fma-avx2`` and ``fma-scalar`` give the same bits, tested)."""
    def key(segment: dict) -> tuple:
        products = str(segment.get("products"))
        return (segment.get("mode"), segment.get("kernels"), segment.get("mkl_branch"),
                "fma" if products.startswith("fma-") else products)

    return key(a) == key(b)


class RunContext:
    """One population's run as its folders see it (the module's docstring)."""

    def __init__(self, cfg: RunConfig, out_dir: Path, seeds: tuple[int, ...], member_settings: dict,
                 settings: dict | None, checkpoint_path: Path, start: float, compiled: dict, stop: StopSignals):
        self.cfg, self.out_dir, self.seeds, self.settings = cfg, Path(out_dir), seeds, settings
        self.member_settings, self.checkpoint_path, self.start = member_settings, checkpoint_path, start
        self.compiled, self.stop = compiled, stop
        if compiled["enabled"]:
            compiling.configure(cfg.numerics)  # from a clean slate, so a run compiles the same in any process
        self.compile_start = compiling.seconds_spent() if compiled["enabled"] else 0.0
        self.earlier_compile = 0.0
        self.first, self.timing = 0, {"rollout_s": 0.0, "train_s": 0.0}
        self.saved: int | None = None  # the episode the last checkpoint holds
        self.progress: Progress | None = None

    # ------------------------------------------------------------------ before the loop
    def resume(self, run, payload: dict | None) -> int:
        """The members' folders and records for the built ``run`` (``engine.setup.build``), and ``payload``'s
        state where a checkpoint is continued; returns the first episode to train."""
        cfg, phases = self.cfg, run.learner.phases
        self.run = run
        self.members = [Member(s, member_folder(cfg, self.out_dir, s), self.member_settings[s]) for s in self.seeds]
        for member in self.members:
            files.folder(member.folder, self.out_dir, create=True)
        self.parts = run.learner.state_parts()
        self.cpu_start = time.process_time()  # this process's CPU time (every thread): the run's compute
        self.earlier_wall: float | None = 0.0  # wall time of the sessions before a resume (None: not recorded)
        self.earlier_cpu: float | None = 0.0  # CPU time of the sessions before a resume (None: not recorded)
        self.code = dict(code_version())
        self.segments = [numerics_segment(0)]  # the products each session computed with (a new one where they differ)
        self.paths = [{"from_episode": 0, "collector": cfg.env.collector, **phases.path}]  # what ran (likewise)
        if phases.code_refusal:
            print(f"Note: the fused update steps are off because {phases.code_refusal}: the loss module computes "
                  "this run's updates, at its own speed (summary.json's paths records it)", file=sys.stderr)
        elif "loss module" in (phases.path.get("critic"), phases.path.get("actor")):
            from learners import fast_paths

            unrun = fast_paths.own_edits(getattr(phases, "fast_path_code", ()))
            if unrun:  # an edit to a fast path's own code, in a run that takes the loss module's path: it does not run
                self.paths[-1]["edits_not_run"] = unrun
                print(f"Note: {', '.join(unrun[:3])}{f' and {len(unrun) - 3} more' if len(unrun) > 3 else ''} changed, "
                      f"but this run's updates are the loss module's ({phases.path.get('why') or phases.path.get('actor_why')}):"
                      " that edit does not run here; edit the loss module (its class, or the TorchRL loss it inherits) "
                      "for this mode", file=sys.stderr)
        if payload is not None:
            self._continue(payload)
        self.earlier_compile = self.timing.pop("compile_s", 0.0)
        return self.first

    def _continue(self, payload: dict) -> None:
        run = self.run
        if payload.get("starts") != run.starts:  # algo.td.start_from's files changed since the run began
            raise ConfigError(f"{self.checkpoint_path} began from other weights than algo.td.start_from (or "
                              "start_critics_from) holds now; put back the start it recorded, or pass overwrite=true "
                              "to start afresh from what is there now")
        self.first, self.timing = _restore(payload, self.parts, run.env, run.generators, run.learner.phases,
                                           self.members)
        self.saved = self.first
        earlier_paths = [dict(path) for path in payload.get("paths") or []]
        if earlier_paths and {k: v for k, v in earlier_paths[-1].items() if k != "from_episode"} == \
                {k: v for k, v in self.paths[0].items() if k != "from_episode"}:
            self.paths = earlier_paths
        else:
            self.paths = [*earlier_paths, {**self.paths[0], "from_episode": self.first}]
        # a checkpoint from before the record: its products are unknown, so this session's are a segment of their own
        self.segments = [dict(seg) for seg in payload.get("numerics") or []] or [{"from_episode": 0, "recorded": False}]
        now = numerics_segment(self.first)
        if not same_numerics(self.segments[-1], now):
            self.segments.append(now)
        self.earlier_wall = self.timing.pop("wall_s", None)
        self.earlier_cpu = self.timing.pop("cpu_s", None)
        earlier = payload.get("code") or {"source": None}
        if earlier.get("source") != self.code["source"]:  # this run mixes two versions of the code
            self.code["resumed_from"] = {k: v for k, v in earlier.items() if k != "resumed_from"}
        elif earlier.get("resumed_from"):
            self.code["resumed_from"] = earlier["resumed_from"]

    def compile_time(self) -> dict:
        """Seconds spent compiling, every session of a resumed run included."""
        if not self.compiled["enabled"]:
            return {}
        return {"compile_s": self.earlier_compile + compiling.seconds_spent() - self.compile_start}

    # ------------------------------------------------------------------ around the loop
    @contextlib.contextmanager
    def training(self, collector, on_start=None):
        """The members' metrics files and the progress line, open while the loop runs; ``on_start()`` once
        they are. A second signal (or Ctrl-C outside ``StopSignals``) stops the run at once, in one line."""
        columns = metric_columns(self.run.learner.phases) + ([DETERMINISTIC_COLUMN] if self.cfg.eval_every else [])
        try:
            for member in self.members:
                member.metrics = MetricsWriter(member.folder, columns, self.cfg.logger, keep_rows=len(member.rewards),
                                               expect=member.rows)
            if on_start is not None:
                on_start()
            self.progress = _progress(self.cfg, self.seeds, initial=self.first)
            yield
        except KeyboardInterrupt as err:
            if isinstance(err, RunStopped):
                raise
            raise RunStopped(_stopped(self.stop.requested or "SIGINT", None, self.cfg.episodes, self.saved,
                                      self.checkpoint_path)) from None
        finally:
            if self.progress is not None:
                self.progress.close()
            for member in self.members:
                if member.metrics is not None:
                    member.metrics.close()
            collector.shutdown()

    @property
    def running(self) -> bool:
        """Whether any member still trains (the others diverged)."""
        return any(m.status == "running" for m in self.members)

    def timed(self, key: str) -> "_timer":
        return _timer(self.timing, key)

    def freeze(self, failed: dict[int, str], episode: int) -> None:
        """Record and freeze the members that diverged in the last phase."""
        for r, reason in sorted(failed.items()):
            self.members[r].status, self.members[r].failure = "diverged", {"episode": episode, "reason": reason}
            self.run.learner.phases.freeze(r)

    def log(self, episode: int, batch: TensorDictBase, totals: MetricTotals) -> None:
        """Episode ``episode``'s rows (its returns and the update's diagnostics), the progress line, and a
        checkpoint when one is due or a stop was asked for (then ``RunStopped``)."""
        cfg, members = self.cfg, self.members
        diagnostics = totals.means(len(members))
        scored = cfg.eval_every and (episode + 1) % cfg.eval_every == 0  # the policy as it stands after the episode
        for r, member in enumerate(members):
            if member.status == "running":
                row = {**_episode_results(episode, batch, r), **diagnostics[r]}
                if scored:  # reads the weights only: no generator, no training state
                    row[DETERMINISTIC_COLUMN] = _own_track_score(
                        cfg, member.seed, *_deterministic_policy(cfg, self.run.learner.member_weights(r)))
                member.metrics.write(row)
                member.rewards.append(row["total_reward"])
        _show(self.progress, members, max(1, min(cfg.final_window, cfg.episodes)))
        done = episode + 1
        stopping = self.stop.requested is not None and done < cfg.episodes
        if cfg.checkpoint_every and done < cfg.episodes and (done % cfg.checkpoint_every == 0 or stopping):
            so_far = {**({} if self.earlier_wall is None else
                         {"wall_s": self.earlier_wall + time.perf_counter() - self.start}),
                      **({} if self.earlier_cpu is None else
                         {"cpu_s": self.earlier_cpu + time.process_time() - self.cpu_start})}
            run = self.run
            payload = _payload(done, {**self.timing, **so_far, **self.compile_time()}, self.settings, self.parts, run.env,
                               self.code, self.segments, self.paths, run.generators, run.learner.phases, members,
                               run.learner.sampler)
            checkpoint.save(self.checkpoint_path, {**payload, "starts": run.starts})  # what its networks started from
            self.saved = done
        if stopping:
            raise RunStopped(_stopped(self.stop.requested, done, cfg.episodes, self.saved, self.checkpoint_path))

    # ------------------------------------------------------------------ after the loop
    def finish(self) -> list[dict]:
        """Each member's weights (a completed one's) and its sealed summary; the checkpoint removed."""
        cfg, run, members = self.cfg, self.run, self.members
        summaries = []
        session = round(time.perf_counter() - self.start, 3)
        # wall_time_s and cpu_time_s cover every session of a resumed run (None if its checkpoint did not
        # record them); both are the process's, for all the members it trained (population.size)
        wall = round(session + self.earlier_wall, 3) if self.earlier_wall is not None else None
        cpu = round(time.process_time() - self.cpu_start + self.earlier_cpu, 3) if self.earlier_cpu is not None else None
        session_wall = {"wall_time_session_s": session} if self.first else {}
        for member in members:  # before anything is written: a run seals the rows it wrote, or nothing
            member.metrics.check_unchanged()
        for r, member in enumerate(members):
            if member.status == "running":
                member.status = "completed"
            weights = run.learner.member_weights(r) if member.status == "completed" else {}
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
                "resumed_at": self.first or None,
                **{f"time/{key}": round(value, 3) for key, value in {**self.timing, **self.compile_time()}.items()},
                "population": {"seeds": list(self.seeds), "size": len(self.seeds)},
                **({"evaluation": evaluation} if evaluation is not None else {}),
                **({"start": run.starts[r]} if run.starts else {}),
                **({"track_file": run.env.sim.file_track.reading.record()} if run.env.sim.file_track is not None
                   else {}),
                "code": self.code, "software": software_versions(), "numerics": _numerics_record(self.segments),
                "compile": self.compiled, "paths": self.paths, "settings": member.settings,
                "files": file_record(member.folder, rundir.RECORDED_FILES),  # what this summary stands for
            }
            summaries.append(write_summary(member.folder, summary))
        files.remove(self.checkpoint_path)  # the runs are finished: summaries and weights remain
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
    from engine.evaluation import evaluate

    policy, settings = _deterministic_policy(cfg, weights)
    own = _own_track_score(cfg, seed, policy, settings)
    others = evaluate(policy, settings, list(cfg.eval_seeds), cfg.eval_episodes)
    return {"episodes": cfg.eval_episodes, "own_track": own, "tracks": {str(k): v for k, v in others.items()},
            "mean": _mean(list(others.values()))}


def _deterministic_policy(cfg: RunConfig, weights: dict):
    """The member's deterministic policy as ``evaluate.py`` builds it from its files, and the settings
    ``engine.evaluation.evaluate`` reads."""
    from engine.evaluation import make_policy
    from racing.config import RacingConfig

    network = {"actor_hidden": list(cfg.network.actor_hidden), "activation": cfg.network.activation}
    policy = make_policy(cfg.algo.loss, network, RacingConfig(**cfg.env.options).obs_size, weights["actor"],
                         cfg.env.past_steps, algo=cfg.algo, critic=weights["critic"], gamma=cfg.gamma)
    settings = {"env": {"options": dict(cfg.env.options), "nearest_ray": cfg.env.nearest_ray}}
    settings["env"].update(track=cfg.env.track, track_file=cfg.env.track_file, track_scale=cfg.env.track_scale,
                           track_closed=cfg.env.track_closed)
    return policy, settings


def _own_track_score(cfg: RunConfig, seed: int, policy, settings: dict) -> float:
    """The deterministic policy's mean total reward over ``cfg.eval_episodes`` episodes on the member's own
    track (start states from seeds 0, 1, ...): the end-of-run evaluation's, and ``eval_every``'s."""
    from engine.evaluation import evaluate, own_track

    track = own_track({"env": settings["env"], "seed": seed})
    return evaluate(policy, settings, [track], cfg.eval_episodes)[track]


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


def _show(progress: Progress, members: list[Member], window: int) -> None:
    """The last episode's reward and the mean of the last ``window`` (the final performance's window: the
    label says how many, ``last10`` in a 10-episode run), over the running members."""
    running = [m for m in members if m.status == "running" and m.rewards]
    diverged = sum(m.status == "diverged" for m in members) or None
    if not running:
        progress.update(diverged=diverged)
        return
    last = _mean([m.rewards[-1] for m in running])
    recent = _mean([_mean(m.rewards[-window:]) for m in running])
    progress.update(**{"reward": last, f"last{window}": recent, "diverged": diverged})
