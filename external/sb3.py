"""Stable-Baselines3's SAC and PPO, with their own defaults, on ``racing/Racing-v0``: outside
reference learners, written as run folders the report reads like this project's.

One run per track seed: ``gym.make("racing/Racing-v0", track_seed=seed)`` (or, with
``random_tracks``, ``track_seed=None``: a new track every episode, the benchmark's training; the
seed then seeds the run and its first reset) (200-step episodes
ending by truncation, which SB3 bootstraps through), SB3's algorithm with every hyperparameter
at its default (``"MlpPolicy"``: 256x256 networks for SAC, 64x64 for PPO; SAC: one gradient
step per environment step, batch 256, gamma 0.99, learned temperature; PPO: 2048-step rollouts,
10 epochs of minibatches of 64, gamma 0.99, GAE 0.95), seeded with the track seed, on one torch
thread, for ``episodes`` episodes (the paper's budget: 201). The first episode starts from
``reset(seed=track seed)``, as a run of ``train.py`` does.

A run's folder holds ``metrics.csv`` (one row per episode: total reward, crashes, final
checkpoint; SB3's losses are not recorded), ``summary.json`` (final performance over the last
``final_window`` episodes, status, timing, code and software versions, SB3's included, numerics,
and the settings: the script's arguments and SB3's hyperparameters as the model holds them)
and ``model.zip`` (SB3's own format). A folder holding a finished run of the same settings is
skipped; there is no checkpoint, so a killed run starts again.
"""

from __future__ import annotations

import io
import math
import time
from pathlib import Path

from engine import rundir
from engine.outputs import EPISODE_COLUMNS, MetricsWriter, file_record, write_atomic, write_summary

ALGOS = ("sac", "ppo")
# The hyperparameters recorded in summary.json, as the SB3 model holds them after construction.
RECORDED = ("learning_rate", "gamma", "batch_size", "buffer_size", "learning_starts", "tau", "train_freq",
            "gradient_steps", "ent_coef", "target_entropy", "n_steps", "n_epochs", "gae_lambda", "clip_range",
            "vf_coef", "max_grad_norm", "use_sde")


class BaselineError(ValueError):
    """An argument the baseline cannot run with."""


MODEL_LIMIT = 1 << 30  # bytes of a model.zip read (SB3's default networks: well under 10 MB)
ENTRY_LIMITS = {"data": 1 << 24, "policy.pth": 1 << 28}  # bytes of the entries read, unpacked (SB3's: KB and MB)
# Which policy class a zip's "policy_class" names, read as text (its "__module__" and the class whose
# __init__ it records), never unpickled: each known class is built here from the zip's plain settings.
POLICIES = {("stable_baselines3.sac.policies", "SACPolicy"): "SAC",
            ("stable_baselines3.td3.policies", "TD3Policy"): "TD3",
            ("stable_baselines3.common.policies", "ActorCriticPolicy"): "PPO"}  # PPO and A2C share their policy
POLICY_KEYS = {"net_arch", "use_sde", "log_std_init", "use_expln", "clip_mean", "n_critics",
               "share_features_extractor", "ortho_init", "full_std", "squash_output", "normalize_images"}


class ModelRefused(ValueError):
    """A model.zip that cannot be loaded as weights alone; the message names it and says why."""


def load_model(path) -> tuple[object, str]:
    """``(policy, algorithm)`` of a Stable-Baselines3 ``model.zip`` loaded as weights only: its plain
    JSON settings (``data``) choose one of ``POLICIES`` and its layers, the policy is built here for
    the racing environment's spaces, and its tensors (``policy.pth``) are loaded with
    ``torch.load(weights_only=True)``. Nothing in the zip is unpickled, so nothing in it runs: a zip
    whose policy needs an unpickled setting (a custom class, activation or feature extractor) is
    refused with one sentence (``ModelRefused``), as is any zip not made for this environment."""
    import io
    import json
    import re
    import zipfile

    from engine.checkpoint import load_tensors_from
    from door import files
    from racing.gym_env import RacingEnv

    try:
        data = files.read(path, MODEL_LIMIT, "Stable-Baselines3 model.zip", follow=True)
    except FileNotFoundError:
        raise ModelRefused(f"{path} does not exist (a Stable-Baselines3 model.zip was expected)") from None
    except (OSError, files.FileRefused) as err:
        raise ModelRefused(str(err)) from None

    def entry(name: str) -> bytes:
        info = archive.getinfo(name)
        if info.file_size > ENTRY_LIMITS[name]:
            raise ModelRefused(f"{path}: its {name} unpacks to {info.file_size:,} bytes, more than a model holds")
        return archive.read(info)

    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            settings = json.loads(entry("data"))
            weights = entry("policy.pth")
    except ModelRefused:
        raise
    except (zipfile.BadZipFile, KeyError, json.JSONDecodeError, UnicodeDecodeError, ValueError, OSError,
            EOFError, RuntimeError, RecursionError, zipfile.LargeZipFile) as err:
        raise ModelRefused(f"{path} is not a Stable-Baselines3 model.zip ({type(err).__name__}: "
                           f"{str(err)[:120]})") from None
    if not isinstance(settings, dict) or not isinstance(settings.get("policy_class"), dict):
        raise ModelRefused(f"{path} is not a Stable-Baselines3 model.zip (its data names no policy class)")
    named = settings["policy_class"]
    module = str(named.get("__module__", ""))
    found = re.match(r"<function (\w+)\.__init__", str(named.get("__init__", "")))
    algo = POLICIES.get((module, found.group(1) if found else ""))
    if algo is None:
        raise ModelRefused(f"{path}: its policy ({module}.{found.group(1) if found else '?'}) is not one of "
                           f"Stable-Baselines3's MlpPolicy classes this tool builds (SAC, TD3/DDPG, PPO/A2C); other "
                           "policies would have to be unpickled, which could run code, so it is refused")
    kwargs = settings.get("policy_kwargs") or {}
    bad = [key for key, value in kwargs.items() if key not in POLICY_KEYS or not _plain(value)] \
        if isinstance(kwargs, dict) else ["policy_kwargs"]
    if bad:
        raise ModelRefused(f"{path}: its policy settings {bad} need unpickling (a custom class or function), which "
                           "could run code; only plain settings (net_arch, use_sde, ...) are loaded")
    problem = _layers_problem(kwargs.get("net_arch"))
    if problem:
        raise ModelRefused(f"{path}: its net_arch {json.dumps(kwargs.get('net_arch'))[:120]} {problem}; nothing was built")
    critics = kwargs.get("n_critics", 2)
    if isinstance(critics, bool) or not isinstance(critics, int) or not 1 <= critics <= MAX_CRITICS:
        raise ModelRefused(f"{path}: its n_critics {json.dumps(critics)[:40]} is not a count of 1 to {MAX_CRITICS} "
                           "Q-networks; nothing was built")
    needed = 4 * least_parameters(algo, kwargs.get("net_arch"), critics if algo != "PPO" else 0)
    if needed > len(weights) + (1 << 16):  # the product that costs, bounded by the bytes that must hold it
        raise ModelRefused(f"{path}: its policy settings build at least {needed:,} bytes of weights, more than its "
                           f"policy.pth holds ({len(weights):,}); nothing was built")
    env = RacingEnv()
    for key, space in (("observation_space", env.observation_space), ("action_space", env.action_space)):
        saved = settings.get(key) if isinstance(settings.get(key), dict) else {}
        if list(saved.get("_shape") or []) != list(space.shape) or saved.get("dtype") != str(space.dtype):
            raise ModelRefused(f"{path}: its {key.replace('_', ' ')} is {saved.get('_shape')} {saved.get('dtype')}, "
                               f"not the racing environment's {list(space.shape)} {space.dtype}")
    env.close()
    if algo == "SAC":
        from stable_baselines3.sac.policies import SACPolicy as policy_class
    elif algo == "TD3":
        from stable_baselines3.td3.policies import TD3Policy as policy_class
    else:
        from stable_baselines3.common.policies import ActorCriticPolicy as policy_class
    try:
        policy = policy_class(env.observation_space, env.action_space, lambda _: 0.0, **kwargs)
    except (TypeError, ValueError, AssertionError, RuntimeError, KeyError) as err:
        raise ModelRefused(f"{path}: its policy settings do not build a {algo} policy ({str(err)[:120]})") from None
    try:
        state = load_tensors_from(io.BytesIO(weights), f"{path}'s policy.pth", "policy's weights")
        policy.load_state_dict(state, strict=True)
    except (ValueError, RuntimeError, TypeError, AttributeError) as err:
        raise ModelRefused(f"{path}: its policy.pth is not the weights of its policy ({str(err).splitlines()[0][:200]})"
                           ) from None
    policy.set_training_mode(False)
    return policy, algo


MAX_LAYERS, MAX_UNITS = 16, 4096  # an SB3 policy's hidden layers and their units (its defaults: 2 of 64 or 256)
MAX_CRITICS = 64  # an SB3 SAC/TD3 policy's Q-networks (its default: 2)
OBS_SIZE, ACTION_SIZE = 6, 2  # the racing environment's (checked against the zip's spaces before anything is built)


def least_parameters(algo: str, net_arch, critics: int) -> int:
    """The fewest parameters an SB3 policy of these settings holds (its actor's layers, and each of its
    ``critics`` Q-networks' once): what its weights file must at least hold, float32 (SB3's defaults when
    ``net_arch`` is None: 256-256 for SAC/TD3, 64-64 for PPO)."""
    default = [64, 64] if algo == "PPO" else [256, 256]
    arch = net_arch if net_arch is not None else default
    pi = arch.get("pi", default) if isinstance(arch, dict) else arch
    qf = (arch.get("vf" if algo == "PPO" else "qf", default) if isinstance(arch, dict) else arch)

    def mlp(inputs: int, widths, outputs: int) -> int:
        sizes = [inputs, *widths, outputs]
        return sum((a + 1) * b for a, b in zip(sizes, sizes[1:]))

    return mlp(OBS_SIZE, pi, ACTION_SIZE) + max(critics, 1 if algo == "PPO" else 0) * mlp(
        OBS_SIZE + (0 if algo == "PPO" else ACTION_SIZE), qf, 1)


def _layers_problem(net_arch) -> str | None:
    """Why an SB3 ``net_arch`` is not a size to build (None: it is): a list of layer widths, or a dict of
    such lists (``pi``, ``vf``, ``qf``), at most ``MAX_LAYERS`` layers of 1 to ``MAX_UNITS`` units."""
    if net_arch is None:
        return None
    lists = list(net_arch.values()) if isinstance(net_arch, dict) else [net_arch]
    if isinstance(net_arch, dict) and not set(net_arch) <= {"pi", "vf", "qf"}:
        return "names networks other than pi, vf and qf"
    for widths in lists:
        if not isinstance(widths, list) or len(widths) > MAX_LAYERS:
            return f"is not a list of at most {MAX_LAYERS} layer widths"
        if any(isinstance(w, bool) or not isinstance(w, int) or not 1 <= w <= MAX_UNITS for w in widths):
            return f"has a layer width outside 1..{MAX_UNITS}"
    return None


def _plain(value) -> bool:
    """Whether a JSON value is plain data (no SB3 ``:serialized:`` object inside)."""
    if isinstance(value, dict):
        return ":serialized:" not in value and ":type:" not in value and all(_plain(v) for v in value.values())
    if isinstance(value, list):
        return all(_plain(v) for v in value)
    return isinstance(value, (str, int, float, bool, type(None)))


def run_folder(out: Path, algo: str, seed: int) -> Path:
    """``<out>/sb3_<algo>/default/seed<seed>``: the report's cell is (sb3_<algo>, default)."""
    return Path(out) / f"sb3_{algo}" / "default" / f"seed{seed}"


def settings_of(algo: str, seed: int, episodes: int, final_window: int, numerics_mode: str,
                random_tracks: bool = False) -> dict:
    """What decides a run's numbers, before SB3's own hyperparameters are added (``track: random`` only
    for a run on random tracks, so that the settings of earlier runs on their seed's track stay as
    they were recorded)."""
    if algo not in ALGOS:
        raise BaselineError(f"algo must be one of {', '.join(ALGOS)}, got {algo!r}")
    if episodes < 1 or final_window < 1:
        raise BaselineError(f"episodes and final_window must be at least 1, got {episodes} and {final_window}")
    if not 0 <= seed < 2**32:
        raise BaselineError(f"track seeds are in [0, 2**32), got {seed}")
    settings = {"baseline": "stable-baselines3", "algo": algo, "seed": seed, "episodes": episodes,
                "final_window": final_window, "numerics": numerics_mode, "threads": 1}
    return {**settings, "track": "random"} if random_tracks else settings


def _hyperparameters(model) -> dict:
    values = {}
    for name in RECORDED:
        if hasattr(model, name):
            value = getattr(model, name)
            if callable(value):  # SB3 turns constant schedules into functions
                value = value(1.0)
            values[name] = value if isinstance(value, (int, float, str, bool, type(None))) else repr(value)
    values["net_arch"] = repr(model.policy.net_arch) if hasattr(model.policy, "net_arch") else None
    return values


def train(algo: str, seed: int, episodes: int, out: Path, final_window: int = 20,
          numerics_mode: str = "portable", random_tracks: bool = False) -> dict:
    """Train one SB3 run into its folder (``run_folder``); returns its summary (an earlier
    finished run of the same settings is returned without training; a finished run of other
    settings or a damaged folder is refused, ``BaselineError``). In a fresh process this sets
    the numerics before anything loads torch; in one that has, it checks them."""
    from engine import numerics

    numerics.apply(numerics_mode)
    settings = settings_of(algo, seed, episodes, final_window, numerics_mode, random_tracks)
    folder = run_folder(out, algo, seed)
    with rundir.lock([folder]):  # the folder's rules are train.py's (engine.rundir)
        found = rundir.state(folder)
        if found.kind == "damaged":
            raise BaselineError(found.refusal().replace(", or pass overwrite=true to clear the folder and start "
                                                        "afresh", ""))
        if found.kind == "finished":
            if {k: v for k, v in (found.summary.get("settings") or {}).items() if k != "sb3"} == settings:
                return found.summary
            raise BaselineError(f"{folder} holds a finished run of other settings; choose another --out or move "
                                "it away")
        rundir.clear(folder)  # an unfinished run's rows: SB3 runs restart from the beginning
        return _train(algo, seed, episodes, folder, final_window, numerics_mode, settings, random_tracks)


def _train(algo: str, seed: int, episodes: int, folder: Path, final_window: int, numerics_mode: str,
           settings: dict, random_tracks: bool = False) -> dict:
    import gymnasium as gym
    import stable_baselines3
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.logger import Logger

    import racing
    from engine import numerics
    from engine.version import code_version, software_versions

    # random tracks: a new track per episode, from the env's generator (seeded by the first reset)
    env = gym.make(racing.ENV_ID, track_seed=None if random_tracks else seed)
    kind = {"sac": stable_baselines3.SAC, "ppo": stable_baselines3.PPO}[algo]
    model = kind("MlpPolicy", env, seed=seed, device="cpu", verbose=0)
    # No output of SB3's own logger (it would make an empty folder in the temporary directory per run):
    # the run's metrics are written below.
    model.set_logger(Logger(folder=None, output_formats=[]))
    settings["sb3"] = _hyperparameters(model)
    metrics = MetricsWriter(folder, list(EPISODE_COLUMNS))
    rewards: list[float] = []

    class Episodes(BaseCallback):
        """Writes each finished episode's row; stops training after ``episodes`` episodes."""

        def __init__(self):
            super().__init__()
            self.total, self.crashes = 0.0, 0

        def _on_step(self) -> bool:
            info = self.locals["infos"][0]
            self.total += float(self.locals["rewards"][0])
            self.crashes += int(info["crashed"])
            if not self.locals["dones"][0]:
                return True
            metrics.write({"episode": len(rewards), "total_reward": self.total, "crashes": self.crashes,
                           "final_checkpoint": int(info["checkpoint"])})
            rewards.append(self.total)
            self.total, self.crashes = 0.0, 0
            return len(rewards) < episodes

    start, cpu_start = time.perf_counter(), time.process_time()
    try:
        model.learn(total_timesteps=episodes * env.unwrapped.config.max_steps + 1, callback=Episodes())
    finally:
        metrics.close()
        env.close()
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    buffer = io.BytesIO()
    model.save(buffer)
    write_atomic(folder / "model.zip", buffer.getvalue())
    window = rewards[-final_window:]
    summary = {
        "algo": f"sb3_{algo}", "er": "default", "seed": seed, "episodes": len(rewards),
        "episodes_planned": episodes, "final_mean": math.fsum(window) / len(window) if window else None,
        "final_window": len(window), "status": "completed" if len(rewards) == episodes else "incomplete",
        "diverged": None, "wall_time_s": round(wall, 3), "cpu_time_s": round(cpu, 3), "resumed_at": None,
        "population": {"seeds": [seed], "size": 1},
        "code": code_version(),
        "software": {**software_versions(), "stable_baselines3": stable_baselines3.__version__},
        "numerics": numerics.in_effect(), "compile": {"requested": False, "enabled": False, "reason": None},
        "settings": settings, "files": file_record(folder, ("metrics.csv", "model.zip")),
    }
    return write_summary(folder, summary)
