"""Load a trained run's policy, evaluate it deterministically, film it driving."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import torch

import learners.td
from learners.solo import GaussianPolicyNet
from engine import numerics
from engine.outputs import RunFolderError, first_line  # RunFolderError: part of this module's interface
from racing.config import RacingConfig
from racing.gym_env import RacingEnv
from racing.history import History, past_size


class Policy:
    """A trained run's deterministic policy: ``observation (numpy) -> action in [-1, 1]``.

    The paper's algorithms act with the Gaussian's mean (clipped); SAC, TQC, CrossQ and REDQ with tanh of
    their Gaussian's mean; TD3 and NAF with their actor's output; a planning learner by planning
    without exploration noise (its module's ``evaluation_policy``: the TD-MPC2-style planner's MPPI). Their
    actors are rebuilt as a population of one (``learners.td.learner``), the networks they were trained as.

    A run trained with ``env.past_steps=k`` keeps its own history of the episode (``racing.history.History``):
    call ``reset()`` at each episode's start (``drive_episode`` does), then the policy once per step;
    it reads the observation with its last k observations and actions, as the run's networks did."""

    def __init__(self, net: torch.nn.Module, stacked: bool, past_steps: int = 0, obs_size: int | None = None):
        """``stacked``: ``net`` is a population of one (the off-policy learners' layout), else the paper's
        ``GaussianPolicyNet``."""
        self.net, self.stacked, self.past_steps = net, stacked, past_steps
        self.history = History(1, past_steps, obs_size) if past_steps else None
        self._start = True

    def reset(self) -> None:
        """The next observation is an episode's first (a policy without past steps ignores it; a planning
        network restarts its plan and its draws)."""
        self._start = True
        restart = getattr(self.net, "reset", None)
        if callable(restart):
            restart()

    @torch.no_grad()
    def __call__(self, observation: np.ndarray) -> np.ndarray:
        if self.history is not None:
            self.history.observe(np.asarray(observation, np.float32)[None], started=[0] if self._start else None)
            self._start = False
            observation = self.history.with_past(self.past_steps)[0]
        action = self.actions(torch.as_tensor(observation, dtype=torch.float32).unsqueeze(0))[0].numpy()
        if self.history is not None:
            self.history.act(action[None])
        return action

    @torch.no_grad()
    def actions(self, observations: torch.Tensor) -> torch.Tensor:
        """The actions ``[N, 2]`` for a batch of network inputs ``[N, inputs]`` (observations, with their past
        where the run reads past steps: no history is kept here)."""
        if not self.stacked:  # the paper's learners: the Gaussian's mean, clipped
            loc, _ = self.net(observations)
            return loc.clamp(-1.0, 1.0)
        out = self.net(observations.unsqueeze(0))  # [member, batch, obs]
        return (torch.tanh(out[0]) if isinstance(out, tuple) else out).clamp(-1.0, 1.0)[0]

    def parameters(self):
        return self.net.parameters()


def load_policy(run_dir: Path) -> tuple[Policy, dict]:
    """The run's final policy and its settings (from summary.json); ``RunFolderError`` saying why
    if the folder does not hold a finished, intact run with an actor (``engine.rundir``). In a process
    that set no numerics mode (the tools set one first), the run's own is set (``engine.numerics.apply``:
    ``NumericsError`` with the remedy if torch loaded under another)."""
    from engine.checkpoint import load_tensors
    from engine.limits import weights_limit
    from engine.rundir import state

    run_dir = Path(run_dir)
    found = state(run_dir)
    if found.kind == "damaged":
        raise RunFolderError(f"{run_dir} is damaged: {found.problem}")
    if found.kind != "finished":
        members = sorted(p.name for p in run_dir.glob("seed*") if (p / "summary.json").is_file())
        if members:
            shown = ", ".join(members[:3]) + (", ..." if len(members) > 3 else "")
            raise RunFolderError(f"{run_dir} is a population's folder, not a run: give one of its members' folders "
                                 f"({shown})")
        raise RunFolderError(f"{run_dir} holds no finished run (no summary.json): give the folder of a finished "
                             "train.py run (e.g. outputs/runs/spg_p_multi/memory/seed2067791)")
    actor_path = run_dir / "actor.pt"
    if not actor_path.exists():
        raise RunFolderError(f"{run_dir} holds no actor.pt (its run {found.summary['status']})")
    settings = found.summary["settings"]
    if numerics.applied() is None:
        numerics.apply(settings.get("numerics", "native") if isinstance(settings, dict) else "native")
    try:
        network, env, loss = settings["network"], settings["env"], settings["algo"]["loss"]
    except (KeyError, TypeError):
        raise RunFolderError(f"{run_dir / 'summary.json'} is not a summary written by train.py "
                             "(its settings lack the network, env or algo)") from None
    problem = track_file_problem(settings)
    if problem:
        raise RunFolderError(f"{run_dir}: {problem}")
    try:
        state_dict = load_tensors(actor_path, "actor", limit=weights_limit(network, "actor"))
    except ValueError as err:
        raise RunFolderError(str(err)) from None
    problem = settings_problem(settings, state_dict)
    if problem:
        raise RunFolderError(f"{run_dir / 'summary.json'}: {problem}")
    critic, critic_path, plans = None, run_dir / "critic.pt", _plans(loss)
    if plans and critic_path.exists():  # its deterministic policy may read its Q-networks too
        try:
            critic = load_tensors(critic_path, "critic", limit=weights_limit(network, "critic"))
        except ValueError as err:
            raise RunFolderError(str(err)) from None
    try:
        policy = make_policy(loss, network, RacingConfig(**env.get("options", {})).obs_size, state_dict,
                             past_steps=env.get("past_steps", 0), algo=settings["algo"], critic=critic,
                             gamma=settings.get("gamma"))
    except Exception as err:  # mismatched shapes or keys
        if plans and critic is None:
            raise RunFolderError(f"{run_dir} holds no critic.pt, which its policy needs ({first_line(err)})") from None
        where = actor_path if critic is None else f"{actor_path} or {critic_path.name}"
        raise RunFolderError(f"{where} is not this run's {'actor' if critic is None else 'actor or critic'} "
                             f"({first_line(err)})") from None
    if not all(torch.isfinite(p).all() for p in policy.parameters()):
        raise RunFolderError(f"{actor_path} holds non-finite weights (the run diverged)")
    return policy, settings


def settings_problem(settings: dict, actor_state: dict) -> str | None:
    """Why a finished run's recorded settings cannot be built into its policy here (None: they can), decided
    before anything is allocated: settings no run could have (``RunConfig.from_record``: types, rules, every
    ceiling), networks and acting (a planner's samples) larger than the memory this machine has available,
    or an actor shaped by
    ``network.actor_hidden`` with more parameters than ``actor.pt`` holds (a record edited to ask for more)."""
    from engine.config import ConfigError, RunConfig
    from engine.limits import PARAMETER_COPIES, _gb, _mlp_parameters, available_bytes, estimate

    try:
        cfg = RunConfig.from_record(settings)
    except ConfigError as err:
        return f"records settings no run could have: {err}"
    parts = estimate(cfg)
    weights = parts["networks"] // (len(cfg.members) * PARAMETER_COPIES)  # one member's parameters, in bytes
    acting = parts["acting"] // len(cfg.members)  # a planner's draws and samples for an episode
    available = available_bytes()
    if available is not None and 2 * weights + acting > available:  # built, then loaded from its state dict
        return (f"its settings ask for networks of {_gb(weights)} ({weights // 4:,} parameters) and {_gb(acting)} "
                f"to act with, more than this machine has available ({_gb(available)})")
    if cfg.algo.learner.networks is None:  # the actor is network.actor_hidden's multilayer perceptron
        asked = _mlp_parameters([cfg.env.observation_size, *cfg.network.actor_hidden, 2])
        held = sum(value.numel() for value in actor_state.values() if isinstance(value, torch.Tensor))
        if asked > held:
            return (f"its settings ask for an actor of at least {asked:,} parameters (network.actor_hidden "
                    f"{list(cfg.network.actor_hidden)}) but actor.pt holds {held:,} numbers")
    return None


def _plans(loss) -> bool:
    """Whether learner ``loss``'s deterministic policy is more than its actor (its module's ``evaluation_policy``);
    False for a name no learner has (``make_policy`` says so)."""
    try:
        learner = learners.spec(loss)
    except ValueError:
        return False
    return learners.FAMILIES[learner.family].OFF_POLICY and hasattr(learner.torch_half(), "evaluation_policy")


def make_policy(loss: str, network: dict, obs_size: int, state: dict, past_steps: int = 0,
                algo: dict | None = None, critic: dict | None = None, gamma: float | None = None) -> Policy:
    """The deterministic policy of an actor's saved weights (``actor.pt``) for ``algo.loss``, with the
    run's ``env.past_steps`` (its networks read ``racing.history.past_size(obs_size, past_steps)`` inputs)
    and its ``algo`` settings (a learner whose actor its own options shape reads them). A learner whose
    deterministic policy is more than its actor (a planner: its module's ``evaluation_policy``) also reads
    the run's critic weights ``critic`` (``critic.pt``) and discount ``gamma``."""
    width = past_size(obs_size, past_steps)
    learner = learners.spec(loss)
    stacked = learners.FAMILIES[learner.family].OFF_POLICY  # the off-policy learners' actors: populations of one
    if stacked:
        from learners.td.learner import make_actor_net
        from learners.networks import NormalisedActor, ObservationNorm, load_member_state_dict

        net = make_actor_net(learner, 1, width, 2, network, algo)
        state = saved_actor(state)
        if any(k.startswith("norm.") for k in state):  # algo.td.observation_norm: the statistics it acted with
            net = NormalisedActor(ObservationNorm(1, width), net)
        load_member_state_dict(net, 0, state)
        own = getattr(learner.torch_half(), "evaluation_policy", None)
        if own is not None:
            net = own(net, critic, network, algo, gamma)
    else:
        net = GaussianPolicyNet(width, 2, network["actor_hidden"], network["activation"])
        net.load_state_dict(state)
    net.eval()
    return Policy(net, stacked, past_steps, obs_size)


def saved_actor(state: dict) -> dict:
    """An off-policy run's saved actor weights under today's names (TorchRL's layout of its parameters, until
    da21af2, prefixed every name with ``module.``)."""
    if state and all(k.startswith("module.") for k in state):
        return {k.removeprefix("module."): v for k, v in state.items()}
    return state


def deterministic_action(policy: Policy, observation: np.ndarray) -> np.ndarray:
    """The policy's action without exploration noise."""
    return policy(observation)


def track_file_problem(settings: dict) -> str | None:
    """Why a run's own track file cannot stand for the track it trained on (None: it can): missing,
    or changed since (its SHA-256 differs from the one the run recorded)."""
    from engine.config import track_file_sha256

    env = settings.get("env") or {}
    if env.get("track") != "file":
        return None
    path, recorded = Path(env.get("track_file") or ""), env.get("track_file_sha256")
    found = track_file_sha256(path)  # bounded: a regular file of a track file's size, never a pipe
    if found is None:
        return (f"the run trained on the track file {path}, which cannot be read here (missing, not a regular file, "
                "or larger than a track file); restore it (a relative path is read from the current folder) to "
                "evaluate the run")
    if recorded is not None and found != recorded:
        return (f"the run trained on the track file {path}, which has changed since (its SHA-256 differs from the "
                "one the run recorded); restore that file to evaluate the run on its own track")
    return None


def own_track(settings: dict):
    """The track a run trained on: its seed, or its track file (``env.track=file``: a
    ``racing.track_file.FileTrack`` with the run's ``env.track_scale`` and ``env.track_closed``)."""
    from racing.track_file import FileTrack

    env = settings.get("env") or {}
    if env.get("track") != "file":
        return settings["seed"]
    return FileTrack(env["track_file"], env.get("track_scale"), env.get("track_closed"))


def make_env(settings: dict, track: int | str, render_mode: str | None = None) -> RacingEnv:
    """A Gymnasium env with the run's environment settings, on a track: a seed or a track file."""
    env = settings["env"]
    from racing.track_file import env_keywords

    return RacingEnv(render_mode=render_mode, nearest_ray=env.get("nearest_ray", False), **env_keywords(track),
                     **env.get("options", {}))


def run_episode(net: Policy, env: RacingEnv, seed: int, frames: list | None = None, name: str | None = None) -> float:
    """One deterministic episode of a trained policy from the start state of ``seed``; its total
    reward (with ``frames``, every rendered frame, the start included, appended to it, with
    ``name`` and the reward so far drawn on each)."""
    return drive_episode(lambda _env, obs: deterministic_action(net, obs), env, seed, frames, reset=net.reset,
                         name=name)


def drive_episode(act, env: RacingEnv, seed: int, frames: list | None = None, reset=None,
                  name: str | None = None) -> float:
    """One episode driven by ``act(env, observation) -> action`` from the start state of ``seed``
    (``reset()``, if given, called once the car is at the start); its total reward. The action is
    checked as the environment checks any; ``frames`` and ``name`` as for ``run_episode``."""
    obs, _ = env.reset(seed=seed)
    if reset is not None:
        reset()
    total, done = 0.0, False

    def take_frame() -> None:
        if frames is not None:
            env.unwrapped.render_lines = ([] if name is None else [name]) + [f"reward so far {total:.1f}"]
            frames.append(env.render())

    take_frame()
    limit = env.unwrapped.config.max_steps
    while not done:
        obs, reward, terminated, truncated, _ = env.step(act(env, obs))
        total += reward
        done = terminated or truncated
        take_frame()
        if frames is not None and limit > 2 * FILM_PROGRESS_EVERY and len(frames) % FILM_PROGRESS_EVERY == 0:
            print(f"  filmed {len(frames):,} of at most {limit + 1:,} frames", file=sys.stderr, flush=True)
    return total


def evaluate(net: Policy, settings: dict, track_seeds: list[int | str], episodes: int,
             seed: int = 0) -> dict[int | str, float]:
    """Mean total reward of ``episodes`` episodes on each track, a seed or a track file (start
    states from ``seed``)."""
    results = {}
    for track in track_seeds:
        env = make_env(settings, track)
        totals = [run_episode(net, env, seed + episode) for episode in range(episodes)]
        results[track] = math.fsum(totals) / len(totals)
        env.close()
    return results


def film(net: Policy, settings: dict, track_seed: int | str, path: Path, seed: int = 0, fps: int = 30,
         name: str | None = None) -> tuple[int, float]:
    """Write one deterministic episode on a track (a seed or a track file) as a GIF or MP4 (by
    suffix), ``name`` (e.g. the run's folder) and the reward so far on each frame; returns the
    number of frames and the episode's total reward."""
    check_video_path(path)
    env = make_env(settings, track_seed, render_mode="rgb_array")
    frames: list = []
    total = run_episode(net, env, seed, frames, name=name)
    env.close()
    return write_video(frames, path, fps), total


def check_video_path(path: Path) -> None:
    """A video is a .gif or an .mp4, written with the render extra; refused before any episode runs."""
    if Path(path).suffix.lower() not in (".gif", ".mp4"):
        raise ValueError(f"video path must end in .gif or .mp4, got {Path(path).name!r}")
    try:
        import imageio.v2  # noqa: F401
    except ImportError:
        raise RuntimeError("writing videos needs the render extra: pip install -c constraints/cpu.txt "
                           "-e '.[render]'") from None


def _padded(frame: np.ndarray, block: int) -> np.ndarray:
    """``frame`` (H, W, 3) with its last rows and columns repeated up to multiples of ``block``."""
    height, width = frame.shape[:2]
    return np.pad(frame, ((0, -height % block), (0, -width % block), (0, 0)), mode="edge")


FILM_PROGRESS_EVERY = 500  # frames between progress lines while filming a long episode (a circuit's)


def write_video(frames: list, path: Path, fps: int = 30) -> int:
    """Frames (RGB arrays) as a GIF or MP4 at ``fps``, encoded in memory and written whole through the
    file door (``door.files.write_atomic``); returns how many."""
    import imageio.v3 as imageio

    from door import files

    path = Path(path)
    if path.suffix.lower() == ".gif":
        data = imageio.imwrite("<bytes>", frames, extension=".gif", duration=1000 / fps, loop=0)
    else:  # the codec takes sides that are multiples of 16: the frames' edges are repeated to fit, never resized
        frames = [_padded(frame, 16) for frame in frames]
        data = imageio.imwrite("<bytes>", frames, extension=".mp4", plugin="FFMPEG", fps=fps, macro_block_size=16)
    files.folder(path.parent, path.parent, create=True)
    files.write_atomic(path, data)
    return len(frames)
