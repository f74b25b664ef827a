"""Typed, validated run configuration, built from the Hydra config before anything else.

The values live in ``conf/`` (one commented YAML per node); these classes hold their types
and rules. ``RunConfig.from_mapping`` rejects unknown keys, wrong types and values the
design does not allow, each in one sentence naming what was expected.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import learners  # torch-free: each family's keys and option blocks
from engine.numerics import MODES as NUMERIC_MODES  # torch-free, like this module
from learners.options import ACTIVATIONS
from learners.options import ConfigError  # noqa: F401 (raised by every check here; part of this module's interface)
from learners.options import at_least as _at_least
from learners.options import build as _build
from learners.options import capped
from learners.options import choice as _choice
from learners.options import positive as _positive

TRACK_SOURCES = ("fixed", "random", "file")
COLLECTORS = ("direct", "torchrl")
LOGGERS = ("csv", "tensorboard", "none")


def seed_dir(seeds, seed) -> str:
    """The run folder's last part (``conf/config.yaml``): ``/seed<seed>`` for one run, nothing
    for a population (its members write ``seed<seed>/`` inside the folder). Checked as a name
    (``door.files.name``) before Hydra makes the folder, as ``run_path``'s parts are."""
    from door import files

    return f"/{files.name(f'seed{seed}', 'seed')}" if seeds is None else ""


def run_path(algo, er, seeds, seed) -> str:
    """A run's folder below ``outputs/runs/`` or a sweep's folder (``conf/config.yaml``):
    ``<algo>/<er>/seed<seed>`` for one run, ``<algo>/<er>`` for a population. The names are checked
    as names (``door.files.name``: no separator, no ``..``) before Hydra makes the folder, so a
    configuration value never makes a folder outside ``outputs/``."""
    from door import files

    parts = [files.name(algo, "algo.name"), files.name(er, "er.name")]
    return "/".join(parts) + seed_dir(seeds, seed)


def register_resolvers() -> None:
    """Make ``${racing_run_path:...}`` and ``${racing_seed_dir:...}`` known to OmegaConf (before Hydra
    composes the config)."""
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("racing_seed_dir"):
        OmegaConf.register_new_resolver("racing_seed_dir", seed_dir)
    if not OmegaConf.has_resolver("racing_run_path"):
        OmegaConf.register_new_resolver("racing_run_path", run_path)


_noted: set[str] = set()
NOTES_SAID = "RACING_NOTES_SAID"  # set by a sweep once its whole-sweep check has said every job's notes


_quiet = False  # set while a recorded run's settings are checked (RunConfig.from_record): its notes were its run's


def _note(message: str) -> None:
    """A one-line note on stderr, once per process (a value accepted, but not as one might expect), and
    once per sweep (its jobs' processes do not say again what the sweep's check said)."""
    if message not in _noted and not os.environ.get(NOTES_SAID) and not _quiet:
        _noted.add(message)
        import sys

        print(f"Note: {message}", file=sys.stderr)


def config_mapping(cfg) -> dict:
    """A composed Hydra config as the plain mapping a run records and validates: resolved, and
    ``env.options`` without the keys left null (conf/config.yaml lists every RacingConfig field
    as null so that ``env.options={...}`` merges on the command line; null means its default), without
    ``algo.title``, a label for tables (``algo_titles``), not part of what a run is."""
    from omegaconf import OmegaConf

    mapping = OmegaConf.to_container(cfg, resolve=True)
    if isinstance(mapping.get("algo"), dict):
        mapping["algo"].pop("title", None)
    env = mapping.get("env")
    if isinstance(env, dict) and isinstance(env.get("options"), dict):
        env["options"] = {k: v for k, v in env["options"].items() if v is not None}
    if isinstance(env, dict):  # how to read a track file, and past steps: recorded only when set
        for key in ("track_scale", "track_closed"):
            if key in env and env[key] is None:
                del env[key]
        if type(env.get("past_steps")) is int and env["past_steps"] == 0:  # (0.0 or false stay, to be refused)
            del env["past_steps"]
    if isinstance(env, dict) and "track_file" in env:  # recorded only when set, with its content's hash
        if env["track_file"] is None:
            del env["track_file"]
        elif "track_file_sha256" not in env:
            env["track_file_sha256"] = track_file_sha256(env["track_file"])
    return mapping


# Keys renamed since runs were first recorded: (node, old name) -> new name. A recorded run's settings
# are read with today's names (``current_names``: read_summary, and run_settings for checkpoints), so an
# old run folder still evaluates, compares and resumes.
RENAMED_KEYS = {("env", "memory"): "past_steps"}  # the observation's past steps; "memory" is the replay memory


def current_names(settings):
    """A recorded run's settings mapping with today's key names (``RENAMED_KEYS``); anything else as given."""
    if not isinstance(settings, dict):
        return settings
    renamed = dict(settings)
    for (node, old), new in RENAMED_KEYS.items():
        inner = renamed.get(node)
        if isinstance(inner, dict) and old in inner and new not in inner:
            renamed[node] = {(new if k == old else k): v for k, v in inner.items()}
    return renamed


def settings_difference(old, new, limit: int = 3) -> str:
    """The keys in which two runs' settings differ, as ``key: old -> new`` (at most ``limit``)."""
    def flat(value, prefix=""):
        if isinstance(value, dict):
            out = {}
            for key, item in value.items():
                out.update(flat(item, f"{prefix}{key}."))
            return out
        return {prefix.rstrip("."): value}

    a, b = flat(old or {}), flat(new or {})
    keys = [k for k in dict.fromkeys([*a, *b]) if a.get(k, "(unset)") != b.get(k, "(unset)")]
    if "env.track_file_sha256" in keys and a.get("env.track_file") == b.get("env.track_file"):
        return (f"its track file {b.get('env.track_file')} has changed since (its SHA-256 differs from the one the "
                "run recorded)")
    shown = [f"{k}: {_short(a.get(k, '(unset)'))} -> {_short(b.get(k, '(unset)'))}" for k in keys[:limit]]
    more = f" and {len(keys) - limit} more" if len(keys) > limit else ""
    return "; ".join(shown) + more if shown else "no key differs"


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def track_file_sha256(path) -> str | None:
    """The SHA-256 of a track file's bytes (None if it is not a regular file of at most the size a
    track file may have, or cannot be read: validation then says why)."""
    import hashlib

    from door import files
    from racing.track_file import MAX_BYTES

    try:
        return hashlib.sha256(files.read(path, MAX_BYTES, "track file", follow=True)).hexdigest()
    except (OSError, TypeError, ValueError):  # a FIFO, a device or a larger file is refused unread (FileRefused)
        return None


def _check_device(device: str) -> None:
    """``cpu``, or ``cuda``/``cuda:N`` when that GPU is present (checked without importing torch for cpu)."""
    if device == "cpu":
        return
    if not (device == "cuda" or (device.startswith("cuda:") and device[5:].isdigit())):
        raise ConfigError(f"device must be cpu, cuda or cuda:<index>, got {device!r}")
    import torch

    index = int(device[5:]) if ":" in device else 0
    if not torch.cuda.is_available() or index >= torch.cuda.device_count():
        raise ConfigError(f"device={device} but torch sees {torch.cuda.device_count()} CUDA device(s) "
                          f"(torch {torch.__version__}); use device=cpu")


@dataclass(frozen=True)
class AlgoConfig:
    """One algorithm (``conf/algo/*.yaml``): its learner (``loss``, ``learners.registry``), the optimisers'
    settings, the keys its family requires (``KEYS``: the paper's protocol's epochs and entropy) and its
    option blocks (``algo.<block>``: its family's and its own, each built into the dataclass that
    declares and checks it; read as ``algo.sac``, ``algo.td``..., None for a block it does not read)."""

    name: str
    loss: str
    critic_lr: float
    actor_lr: float
    adam_eps: float
    minibatch_size: int = capped((10_000_000, "transitions"))
    value_epochs: int | None = None  # the paper's protocol only (ppo, spg)
    policy_epochs: int | None = None
    entropy_coeff: float | None = None
    joint_log_prob: bool | None = None
    blocks: dict = field(default_factory=dict)  # {block: its options}, as given, then built

    def __getattr__(self, name: str):
        if name in block_names():  # an option block: built if this learner reads it, else None
            return self.__dict__.get("blocks", {}).get(name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    @classmethod
    def from_mapping(cls, where: str, values: Mapping[str, Any]) -> "AlgoConfig":
        """From ``conf/algo``'s mapping: the keys of the option blocks the learners declare go to ``blocks``
        (any other unknown key is refused, naming the valid ones)."""
        names = block_names()
        given = {k: v for k, v in values.items() if k not in names}
        blocks = {k: v for k, v in values.items() if k in names}
        if "blocks" in given:
            raise ConfigError(f"{where}: unknown key(s) ['blocks']; give each option block by its name "
                              f"({', '.join(sorted(names))})")
        for key, block in blocks.items():
            if block is not None and not isinstance(block, Mapping):
                raise ConfigError(f"{where}.{key} must be a mapping, got {block!r}")
        return _build(cls, where, {**given, "blocks": {k: dict(v) for k, v in blocks.items() if v is not None}})

    def __post_init__(self) -> None:
        w = f"algo {self.name}"
        _choice(f"{w}: loss", self.loss, learners.LOSSES)
        for key in ("critic_lr", "actor_lr", "adam_eps"):
            _positive(f"{w}: {key}", getattr(self, key))
        _at_least(f"{w}: minibatch_size", self.minibatch_size, 1)
        learner = learners.spec(self.loss)
        family = learners.family(self.loss)
        missing = [key for key in family.KEYS if getattr(self, key) is None]
        if missing:
            raise ConfigError(f"{w}: loss {self.loss} needs {missing}")
        for name, other in learners.FAMILIES.items():
            given = [key for key in other.KEYS if other is not family and getattr(self, key) is not None]
            if given:
                raise ConfigError(f"{w}: {given} belong to {other.DESCRIPTION} (its learners: "
                                  f"{', '.join(learners.in_family(name))}), not to loss {self.loss}; remove them")
        family.check(self, learner)
        learner.check(self)
        reads = {**family.BLOCKS, **learner.blocks}  # what this learner reads: its family's and its own
        built = {}
        for kind in sorted(block_names()):
            block = self.blocks.get(kind)
            if kind in reads:
                if block is None:
                    raise ConfigError(f"{w}: loss {self.loss} needs a '{kind}:' block of options")
                built[kind] = _build(reads[kind], f"{w}: {kind}", block)
            elif block is not None:
                raise ConfigError(f"{w}: a '{kind}:' block does not apply to loss {self.loss}; remove it")
        object.__setattr__(self, "blocks", built)

    @property
    def bootstrapped(self) -> bool:
        """Trained off-policy from a replay memory only, on bootstrapped targets (every learner of ``learners.td``)."""
        return learners.family(self.loss).OFF_POLICY

    @property
    def learner(self):
        """Its learner's declaration (``learners.registry``)."""
        return learners.spec(self.loss)


@functools.cache
def block_names() -> frozenset[str]:
    """Every option block (``algo.<block>``) a family or a learner declares (``learners.registry``: fixed once
    imported, so computed once; ``AlgoConfig.__getattr__`` asks at every read of a block)."""
    return frozenset({*(b for f in learners.FAMILIES.values() for b in f.BLOCKS),
                      *(b for spec in learners.registry.LEARNERS.values() for b in spec.blocks)})


CONF_DIR = Path(__file__).resolve().parent.parent / "conf"


@functools.lru_cache(maxsize=1)
def _algo_files() -> dict[str, dict]:
    """Every ``conf/algo/*.yaml`` as written, by file stem (read once per process)."""
    import yaml

    from door import files

    return {path.stem: yaml.safe_load(files.read_text(path, 1 << 20, "configuration file")) or {}
            for path in sorted((CONF_DIR / "algo").glob("*.yaml"))}


def algo_titles() -> dict[str, str]:
    """Every algorithm of ``conf/algo/`` by name, as tables name it (its ``title:``; else its name).
    The one list of algorithms the report and the leaderboard read: a new ``conf/algo/*.yaml``
    joins them by itself."""
    return {node.get("name", stem): node.get("title") or node.get("name", stem) for stem, node in _algo_files().items()}


def algo_learners() -> dict[str, str]:
    """Every algorithm of ``conf/algo/`` by name, with the learner (``loss:``) it trains, following an
    algorithm built on another (its ``defaults`` list). What a run recorded is checked against it: a run
    whose name is one of these but that trained another learner is not that algorithm's."""
    nodes = _algo_files()
    found = {}
    for stem, node in nodes.items():
        seen = node
        for _ in range(len(nodes)):
            if "loss" in seen:
                break
            bases = [entry for entry in seen.get("defaults") or [] if isinstance(entry, str) and entry != "_self_"]
            seen = nodes.get(bases[0], {}) if bases else {}
        found[node.get("name", stem)] = seen.get("loss")
    return found


@dataclass(frozen=True)
class ERConfig:
    """An experience-replay row of the paper's table (``conf/er/*.yaml``)."""

    name: str
    train_on_memory: bool
    train_on_recent: bool
    minibatch_fraction: float
    buffer_size: int = capped((100_000_000, "transitions per member"))
    priority: dict | None = None  # proportional prioritised sampling of the memory (er=prioritised)

    def __post_init__(self) -> None:
        if self.priority is not None:
            object.__setattr__(self, "priority", _build(PriorityOptions, f"er {self.name}: priority", self.priority))
            if not self.train_on_memory or self.train_on_recent:
                raise ConfigError(f"er {self.name}: priority samples the replay memory: it needs train_on_memory: "
                                  "true and train_on_recent: false")
        if not (self.train_on_memory or self.train_on_recent):
            raise ConfigError(f"er {self.name}: at least one of train_on_memory and train_on_recent "
                              "must be true")
        if not 0 < self.minibatch_fraction <= 1:
            raise ConfigError(f"er {self.name}: minibatch_fraction must be in (0, 1], "
                              f"got {self.minibatch_fraction}")
        _at_least(f"er {self.name}: buffer_size", self.buffer_size, 1)


@dataclass(frozen=True)
class PriorityOptions:
    """Proportional prioritised replay (``collectors.prioritised``): P(i) ~ (|delta_i| + eps)^alpha,
    importance weights (N P(i))^-beta / max."""

    alpha: float
    beta: float
    eps: float

    def __post_init__(self) -> None:
        _at_least("er.priority.alpha", self.alpha, 0)
        if not 0 <= self.beta <= 1:
            raise ConfigError(f"er.priority.beta must be in [0, 1], got {self.beta}")
        _positive("er.priority.eps", self.eps)


@dataclass(frozen=True)
class EnvConfig:
    track: str
    collector: str
    nearest_ray: bool
    options: dict
    track_file: str | None = None  # env.track=file: the CSV file (racing/track_file.py)
    track_file_sha256: str | None = None  # its content, recorded (config_mapping): a changed file is another run
    track_scale: float | None = None  # the file's pixels per file unit (None: its comment, else the width rule)
    track_closed: bool | None = None  # the file is a circuit (None: its comment, else its geometry)
    past_steps: int = 0  # every network reads the observation now and the car's last this-many observations and actions

    def __post_init__(self) -> None:
        _choice("env.track", self.track, TRACK_SOURCES)
        from racing.history import check_steps

        try:
            check_steps("env.past_steps", self.past_steps)
        except ValueError as err:
            raise ConfigError(str(err)) from None
        _choice("env.collector", self.collector, COLLECTORS)
        from racing.config import RacingConfig

        try:
            RacingConfig.from_keywords("env.options", **self.options)
        except (TypeError, ValueError) as err:
            raise ConfigError(str(err)) from None
        if (self.track == "file") != (self.track_file is not None):
            raise ConfigError("env.track=file needs env.track_file=PATH (a track file), and env.track_file needs "
                              f"env.track=file; got env.track={self.track}, env.track_file={self.track_file}")
        if self.track_file is None and (self.track_scale is not None or self.track_closed is not None):
            raise ConfigError("env.track_scale and env.track_closed say how to read env.track_file; set "
                              "env.track=file env.track_file=PATH, or leave them null")
        if self.track_scale is not None and self.track_scale <= 0:  # its type and finiteness: coerce's
            raise ConfigError(f"env.track_scale must be a number > 0 (pixels per file unit), got {self.track_scale!r}")
        if self.track_file is not None:
            from racing.track_file import TrackFileError, file_track

            if "num_segments" in self.options:
                raise ConfigError("env.options.num_segments comes from the track file; remove it")
            try:
                track, options = file_track(self.track_file, dict(self.options), "env.options", self.track_scale,
                                            self.track_closed)
            except (TrackFileError, TypeError, ValueError) as err:
                raise ConfigError(f"env.track_file: {err}") from None
            for warning in track.reading.warnings:  # the car may not fit (tracks.py check says the same)
                _note(f"env.track_file {self.track_file}: {warning}")
            reach = options.max_steps * options.max_speed  # pixels an episode covers at full speed
            length = track.centre_line_length()
            if reach < 0.5 * length:  # the default 200 steps on a real circuit: a few percent of a lap
                needed = int(-(-length // (0.6 * options.max_speed) // 100) * 100)  # at 60% of full speed
                _note(f"env.track_file {self.track_file}: an episode of {options.max_steps:,} steps covers at most "
                      f"{reach / length:.0%} of {'a lap' if track.closed else 'the track'} even at full speed "
                      f"(centre line {length:,.0f} px); env.options.max_steps={needed:,} gives a driver at 60% of "
                      f"full speed the whole of it (python tracks.py check {self.track_file} drives a lap)")
            if self.track_file_sha256 != track_file_sha256(self.track_file):
                raise ConfigError(f"env.track_file {self.track_file} is not the file its run recorded "
                                  "(env.track_file_sha256 differs)")

    @property
    def episode_steps(self) -> int:
        from racing.config import RacingConfig

        return RacingConfig(**self.options).max_steps

    @property
    def observation_size(self) -> int:
        """The width of the observation the networks read: ``env.options``' rays and speed, with
        ``env.past_steps`` past steps (``racing.history.past_size``)."""
        from racing.config import RacingConfig
        from racing.history import past_size

        return past_size(RacingConfig(**self.options).obs_size, self.past_steps)


@dataclass(frozen=True)
class NetworkConfig:
    actor_hidden: tuple[int, ...] = capped((65_536, "units in a hidden layer"), (64, "hidden layers"))
    critic_hidden: tuple[int, ...] = capped((65_536, "units in a hidden layer"), (64, "hidden layers"))
    activation: str

    def __post_init__(self) -> None:
        _choice("network.activation", self.activation, ACTIVATIONS)
        for key in ("actor_hidden", "critic_hidden"):
            sizes = getattr(self, key)
            if not sizes or min(sizes) < 1:
                raise ConfigError(f"network.{key} must be a non-empty list of positive layer sizes, got {list(sizes)}")


@dataclass(frozen=True)
class RunConfig:
    """Everything one training run needs (``conf/config.yaml`` and its groups)."""

    seed: int
    seeds: tuple[int, ...] | None = capped(length=(1_000, "members of a population"))
    episodes: int = capped((10_000_000, "episodes"))
    gamma: float
    final_window: int
    threads: int = capped((4_096, "threads"))
    processes: int = capped((1_000, "processes"))
    device: str
    numerics: str
    compile: bool
    progress: bool
    logger: str
    overwrite: bool
    checkpoint_every: int
    resume_numerics: str
    eval_seeds: tuple[int, ...] | None = capped(length=(100_000, "evaluation tracks"))
    eval_episodes: int = capped((100_000, "episodes per evaluation track"))
    eval_every: int = capped((10_000_000, "episodes"))
    algo: AlgoConfig
    er: ERConfig
    env: EnvConfig
    network: NetworkConfig

    def __post_init__(self) -> None:
        if not 0 <= self.seed < 2**32:
            raise ConfigError(f"seed must be in [0, 2**32) (it is also the track seed), got {self.seed}")
        if self.seeds is not None:
            if not self.seeds:
                raise ConfigError("seeds must be null (one run of `seed`) or a non-empty list of track seeds")
            if max(self.seeds) >= 2**32:
                raise ConfigError(f"seeds must be in [0, 2**32) (they are track seeds), got {max(self.seeds)}")
            repeated = sorted({s for s in self.seeds if self.seeds.count(s) > 1})
            if repeated:
                raise ConfigError(f"seeds lists {repeated} more than once; each member needs its own seed "
                                  "(and run folder)")
        _at_least("episodes", self.episodes, 1)
        if not 0 <= self.gamma <= 1:
            raise ConfigError(f"gamma must be in [0, 1], got {self.gamma}")
        _at_least("final_window", self.final_window, 1)
        _at_least("checkpoint_every", self.checkpoint_every, 0, " (0: never)")
        _at_least("threads", self.threads, 1)
        _at_least("processes", self.processes, 1)
        _check_device(self.device)
        _choice("numerics", self.numerics, NUMERIC_MODES)
        _choice("resume_numerics", self.resume_numerics, ("same", "any"))
        _at_least("eval_episodes", self.eval_episodes, 1)
        _at_least("eval_every", self.eval_every, 0)
        if self.eval_seeds is not None:
            if not self.eval_seeds:
                raise ConfigError("eval_seeds must be null (no evaluation) or a non-empty list of track seeds")
            bad = [s for s in self.eval_seeds if not 0 <= s < 2**32]
            if bad:
                raise ConfigError(f"eval_seeds must be track seeds in [0, 2**32), got {bad}")
        if self.final_window > self.episodes:
            _note(f"final_window={self.final_window} is larger than episodes={self.episodes}: the final performance "
                  f"is the mean of all {self.episodes} episodes (summary.json's final_window says how many)")
        td = self.algo.td
        if td is not None and td.updates_before(self.episodes, self.env.episode_steps) == 0:
            _note(f"algo.td.warmup_episodes={td.warmup_episodes} with episodes={self.episodes}: no gradient step is "
                  "taken, so the run's policy is its initial one (give more episodes than warm-up ones)")
        elif td is not None and td.warmup_episodes:
            scored = min(self.final_window, self.episodes)  # the final performance's episodes: the last ones
            random_scored = td.warmup_episodes - (self.episodes - scored)
            steps = td.warmup_episodes * self.env.episode_steps
            if random_scored > 0:
                _note(f"the final performance averages the last {scored} episodes, {random_scored} of them warm-up "
                      f"episodes of uniform random actions (algo.td.warmup_episodes={td.warmup_episodes}); give more "
                      "episodes, or fewer warm-up ones")
            elif steps > 10_000:  # warm-up counts episodes: long ones (a circuit's) make it long
                _note(f"algo.td.warmup_episodes={td.warmup_episodes} of {self.env.episode_steps:,} steps: {steps:,} "
                      "steps of uniform random actions before the first gradient step (the default 5 episodes are "
                      "1,000 steps at 200 an episode)")
        if td is not None and td.critic_first_episodes and td.critic_first_episodes >= self.episodes - 1:
            _note(f"algo.td.critic_first_episodes={td.critic_first_episodes} with episodes={self.episodes}: the actor "
                  "is held through the whole run (only the critics train)")
        if self.eval_every > self.episodes:
            _note(f"eval_every={self.eval_every} is larger than episodes={self.episodes}: metrics.csv's deterministic "
                  "column stays empty")
        _choice("logger", self.logger, LOGGERS)
        if self.logger == "tensorboard":
            import importlib.util

            if importlib.util.find_spec("tensorboard") is None:
                raise ConfigError("logger=tensorboard needs the tensorboard package: "
                                  "pip install -c constraints/cpu.txt -e '.[tensorboard]' (or use logger=csv)")
        learner = self.algo.learner
        if self.algo.bootstrapped and (self.er.train_on_recent or not self.er.train_on_memory):
            modes = "er=memory or er=prioritised" if learner.prioritised else "er=memory"
            raise ConfigError(f"algo {self.algo.name} trains off-policy on a replay memory; use {modes}, "
                              f"not er={self.er.name}")
        if self.algo.td is not None and self.algo.td.n_step > self.env.episode_steps:
            raise ConfigError(f"algo {self.algo.name}: algo.td.n_step ({self.algo.td.n_step}) is longer than an episode "
                              f"({self.env.episode_steps} steps); at most {self.env.episode_steps}")
        learner.check_run(self)  # its own rules on the run (replay, episode length, compile)
        if self.compile and self.algo.td is not None and self.algo.td.critic_dropout:
            raise ConfigError(f"algo {self.algo.name}: compile=true is not supported with algo.td.critic_dropout "
                              "(each member draws its dropout masks from its own generator); use compile=false")
        if self.compile and self.algo.td is not None and (self.algo.td.privileged_critic or self.algo.td.critic_history):
            raise ConfigError(f"algo {self.algo.name}: compile=true is not supported with algo.td.privileged_critic or "
                              "algo.td.critic_history (the eager step feeds them to the Q-networks); use compile=false")
        minibatch = max(1, round(self.algo.minibatch_size * self.er.minibatch_fraction))
        steps = self.env.episode_steps
        if self.er.train_on_recent and minibatch > steps:
            raise ConfigError(f"a minibatch of {minibatch} is larger than the {steps} transitions of "
                              f"one episode that er={self.er.name} trains on; use at most {steps}")
        if self.er.train_on_memory and minibatch > self.er.buffer_size:
            raise ConfigError(f"a minibatch of {minibatch} is larger than the replay memory "
                              f"({self.er.buffer_size} transitions) that er={self.er.name} trains on")

    @property
    def members(self) -> tuple[int, ...]:
        """The seeds of the runs trained together: ``seeds``, or ``(seed,)`` for one run."""
        return self.seeds if self.seeds is not None else (self.seed,)

    def member_settings(self, settings: dict, seed: int) -> dict:
        """The settings of member ``seed``'s run: those of a solo run of that seed, so a run
        trained in a population and the same run trained alone are recognised as one."""
        return {**settings, "seed": seed, "seeds": None}

    # Keys that change how a run reports or is scheduled, not what it computes (every member
    # computes what its solo run does, so splitting a population over processes changes nothing).
    PRESENTATION_KEYS = ("progress", "logger", "overwrite", "checkpoint_every", "processes", "resume_numerics")
    # Keys that decide only the evaluation after training: a checkpoint of a run continues under other values.
    EVALUATION_KEYS = ("eval_seeds", "eval_episodes")

    # Keys below the top level that choose how a run computes, not what: both collectors give the same
    # batches bit for bit (summary.json's "paths" names the one that ran).
    PATH_KEYS = (("env", "collector"),)

    @classmethod
    def run_settings(cls, settings: dict) -> dict:
        """The part of a config mapping that decides what a run computes (summary.json's ``settings``).
        Applied to a recorded run's settings too, before they are compared with a new run's (a run
        recorded with ``env.collector`` is the same run as one without it)."""
        kept = {k: v for k, v in current_names(settings).items() if k not in cls.PRESENTATION_KEYS and k != "hydra"}
        for outer, inner in cls.PATH_KEYS:
            if isinstance(kept.get(outer), dict) and inner in kept[outer]:
                kept[outer] = {k: v for k, v in kept[outer].items() if k != inner}
        return kept

    @classmethod
    def same_run(cls, recorded, settings: dict | None) -> bool:
        """Whether a recorded run's settings (summary.json's, a checkpoint's) are those of ``settings``."""
        if isinstance(recorded, dict) and isinstance(settings, dict):
            return cls.run_settings(recorded) == cls.run_settings(settings)
        return recorded == settings

    @classmethod
    def training_settings(cls, settings: dict | None) -> dict | None:
        """The part of a run's settings that decides its training (what a checkpoint must match)."""
        return None if settings is None else {k: v for k, v in settings.items() if k not in cls.EVALUATION_KEYS}

    @classmethod
    def from_record(cls, settings: Mapping[str, Any]) -> "RunConfig":
        """A recorded run's settings (summary.json's, a downloaded run's) validated as a run's configuration
        is (types, rules, every ceiling): ``ConfigError`` otherwise. Keys a record leaves out (how the run
        printed, which collector ran, options added since it ran) take their defaults for its algorithm."""
        if not isinstance(settings, Mapping):
            raise ConfigError(f"settings must be a mapping, got {type(settings).__name__}")
        algo = settings.get("algo")
        name = algo.get("name") if isinstance(algo, Mapping) else None
        defaults = _default_mapping(name if isinstance(name, str) and name in _algo_files() else None)

        def fill(recorded, default):
            if isinstance(recorded, Mapping) and isinstance(default, Mapping):
                return {**default, **{key: fill(value, default.get(key)) for key, value in recorded.items()}}
            return recorded

        global _quiet
        _quiet = True
        try:
            return cls.from_mapping(fill(current_names(dict(settings)), defaults))
        finally:
            _quiet = False

    @classmethod
    def compose(cls, *overrides: str) -> "RunConfig":
        """Compose ``conf/config.yaml`` with Hydra overrides (as on the command line) and validate,
        without running Hydra's app (for tests, benchmarks and notebooks)."""
        return cls.from_mapping(cls.compose_mapping(*overrides))

    @staticmethod
    def compose_mapping(*overrides: str) -> dict:
        """The plain mapping train.py records for these overrides (``config_mapping``), unvalidated."""
        from pathlib import Path

        from hydra import compose, initialize_config_dir

        from hydra.core.global_hydra import GlobalHydra

        conf = CONF_DIR
        register_resolvers()
        running = GlobalHydra.instance().hydra  # inside Hydra's app (train.py reading a started run): set aside
        GlobalHydra.instance().clear()
        try:
            with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
                cfg = compose("config", overrides=list(overrides))
        finally:
            GlobalHydra.instance().hydra = running
        return config_mapping(cfg)

    @classmethod
    def from_mapping(cls, cfg: Mapping[str, Any]) -> "RunConfig":
        """Validate a plain mapping (e.g. ``OmegaConf.to_container(cfg, resolve=True)``)."""
        values = {k: v for k, v in cfg.items() if k != "hydra"}
        nodes = {"algo": AlgoConfig.from_mapping, "er": ERConfig, "env": EnvConfig, "network": NetworkConfig}
        for key, node in nodes.items():
            if not isinstance(values.get(key), Mapping):
                raise ConfigError(f"{key} must be a config node (a mapping), got {values.get(key)!r}")
            values[key] = node(key, values[key]) if key == "algo" else _build(node, key, values[key])
        return _build(cls, "config", values)


@functools.lru_cache(maxsize=32)
def _default_mapping(algo: str | None) -> dict:
    """The composed defaults (of ``algo`` where given): what a record's missing keys take."""
    import copy

    return copy.deepcopy(RunConfig.compose_mapping(*([f"algo={algo}"] if algo else [])))
