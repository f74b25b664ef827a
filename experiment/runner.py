"""One training run, start to finish: ``train(cfg, out_dir) -> summary``.

Per episode (see ALGO_SPEC's protocol, as ``collectors.replay`` schedules it):
1. if the schedule trains on memory and the memory is not empty: a phase on the memory;
2. collect one episode with the stochastic policy; its total reward is the learning curve;
3. Monte-Carlo returns; the episode's transitions join the replay memory;
4. if the schedule trains on recent experience: a phase on this episode's transitions.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import torch
from tensordict import TensorDictBase

from collectors import ReplayMemory, add_monte_carlo_returns, episode_transitions
from experiment import checkpoint
from experiment.config import ConfigError, RunConfig
from experiment.factories import (make_env, make_episode_collector, make_loss, make_models,
                                  make_optimisers, make_schedule, seed_everything)
from experiment.outputs import SUMMARY_FILE, MetricsWriter, metric_columns, read_summary, write_json_atomic
from experiment.phases import Diverged, MetricTotals, PhaseRunner
from experiment.version import code_version, software_versions


def run_settings(settings: dict) -> dict:
    """The part of a config mapping that decides what a run computes."""
    return {k: v for k, v in settings.items() if k not in RunConfig.PRESENTATION_KEYS and k != "hydra"}


def finished_run(out_dir: Path, settings: dict, overwrite: bool = False) -> dict | None:
    """The summary of a finished run of these settings in ``out_dir``, if there is one.

    A finished run of other settings raises ``ConfigError`` (its results would be lost)
    unless ``overwrite``. An unfinished run (no summary) is started again.
    """
    summary = read_summary(Path(out_dir))
    if summary is None or summary.get("status") not in ("completed", "diverged"):
        return None
    if summary.get("settings") == run_settings(settings):
        return summary
    if overwrite:
        return None
    raise ConfigError(f"{out_dir} holds a finished run of a different configuration; choose another "
                      "folder (hydra.run.dir=...) or pass overwrite=true to replace it")


def train(cfg: RunConfig, out_dir: Path, settings: dict | None = None) -> dict:
    """Train one run of ``cfg`` and write its outputs into ``out_dir``; returns the summary.

    ``settings`` (the config as a plain mapping) is stored in summary.json and checkpoints to
    recognise the run later. If ``out_dir`` holds a checkpoint of the same settings, the run
    continues from it, exactly as if it had never stopped.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    torch.set_num_threads(cfg.threads)
    seed_everything(cfg.seed)
    settings = run_settings(settings) if settings is not None else None

    env = make_env(cfg)
    models = make_models(cfg, env)
    loss = make_loss(cfg, models)
    optimisers = make_optimisers(cfg, models)
    schedule = make_schedule(cfg)
    memory = ReplayMemory(cfg.er.buffer_size)
    phases = PhaseRunner(loss, optimisers, cfg.algo.value_epochs, cfg.algo.policy_epochs)
    minibatch = schedule.minibatch_size(cfg.algo.minibatch_size)

    parts = {"loss": loss, "actor_optim": optimisers.actor, "critic_optim": optimisers.critic, "memory": memory}
    first, rewards, timing = 0, [], {"rollout_s": 0.0, "train_s": 0.0}
    code = dict(code_version())
    checkpoint_path = out_dir / checkpoint.CHECKPOINT_FILE
    if checkpoint_path.exists():
        payload = checkpoint.load(checkpoint_path)
        first, rewards, timing = _restore(payload, settings, parts, env)
        earlier = payload.get("code") or {"source": None}
        if earlier.get("source") != code["source"]:  # this run mixes two versions of the code
            code["resumed_from"] = {k: v for k, v in earlier.items() if k != "resumed_from"}
        elif earlier.get("resumed_from"):
            code["resumed_from"] = earlier["resumed_from"]
    collector = make_episode_collector(cfg, env, models, episodes=cfg.episodes - first)
    metrics = MetricsWriter(out_dir, metric_columns(loss), cfg.logger, keep_rows=first)

    status, failure = "completed", None
    progress = _progress_bar(cfg, initial=first)
    episodes = iter(collector)
    try:
        for episode in range(first, cfg.episodes):
            totals = MetricTotals()
            try:
                with _timer(timing, "train_s"):
                    if schedule.train_on_memory and len(memory):
                        phases.run(memory.contents(), minibatch, totals)
                with _timer(timing, "rollout_s"):
                    batch = next(episodes)
                    add_monte_carlo_returns(batch, cfg.gamma)
                    recent = episode_transitions(batch)
                    memory.add(recent)
                with _timer(timing, "train_s"):
                    if schedule.train_on_recent:
                        phases.run(recent.clone(), minibatch, totals)
            except Diverged as err:
                status, failure = "diverged", {"episode": episode, "reason": str(err)}
                break
            row = {**_episode_results(episode, batch), **totals.means()}
            metrics.write(row)
            rewards.append(row["total_reward"])
            progress.update(1)
            progress.set_postfix(reward=f"{rewards[-1]:.1f}", last20=f"{_mean(rewards[-20:]):.1f}")
            done = episode + 1
            if cfg.checkpoint_every and done % cfg.checkpoint_every == 0 and done < cfg.episodes:
                checkpoint.save(checkpoint_path, _payload(done, rewards, timing, settings, parts, env, code))
    finally:
        progress.close()
        metrics.close()
        collector.shutdown()

    for name, net in (("actor", models.actor_net), ("critic", models.critic_net)):
        path = out_dir / f"{name}.pt"
        if status == "completed":
            torch.save(net.state_dict(), path)
        else:  # non-finite weights are of no use; no stale file from an earlier run either
            path.unlink(missing_ok=True)
    window = rewards[-cfg.final_window:]
    summary = {
        "algo": cfg.algo.name, "er": cfg.er.name, "seed": cfg.seed,
        "episodes": len(rewards), "episodes_planned": cfg.episodes,
        "final_mean": _mean(window) if window else None, "final_window": len(window),
        "status": status, "diverged": failure,
        "wall_time_s": round(time.perf_counter() - start, 3), "resumed_at": first or None,
        **{f"time/{key}": round(value, 3) for key, value in timing.items()},
        "code": code, "software": software_versions(),
        "settings": settings,
    }
    write_json_atomic(out_dir / SUMMARY_FILE, summary)
    checkpoint_path.unlink(missing_ok=True)  # the run is finished: summary and weights remain
    return summary


def _payload(episodes_done: int, rewards: list[float], timing: dict, settings: dict | None, parts: dict,
             env, code: dict) -> dict:
    return {
        "settings": settings, "code": code, "episodes_done": episodes_done, "rewards": list(rewards),
        "timing": dict(timing),
        **{name: part.state_dict() for name, part in parts.items()},
        "rng": checkpoint.capture_rng(), "sim": checkpoint.arrays_to_tensors(env.sim.state_dict()),
    }


def _restore(payload: dict, settings: dict | None, parts: dict, env) -> tuple[int, list[float], dict]:
    if payload.get("settings") != settings:
        raise ConfigError("the run folder holds a checkpoint of a different configuration; choose another "
                          "folder (hydra.run.dir=...) or pass overwrite=true to start afresh")
    try:
        for name, part in parts.items():
            part.load_state_dict(payload[name])
        env.load_sim_state(checkpoint.arrays_from_tensors(payload["sim"]))
        checkpoint.restore_rng(payload["rng"])
        return int(payload["episodes_done"]), list(payload["rewards"]), dict(payload["timing"])
    except (KeyError, RuntimeError, ValueError, TypeError) as err:
        raise checkpoint.CheckpointError(f"the checkpoint does not fit this run ({type(err).__name__}: "
                                         f"{str(err).splitlines()[0][:200]}); delete it to start afresh") from None


def _episode_results(episode: int, batch: TensorDictBase) -> dict:
    """Learning-curve values of one car's episode (the batch is [1, steps])."""
    return {
        "episode": episode,
        "total_reward": float(batch["next", "reward"].sum(dtype=torch.float64)),
        "crashes": int(batch["next", "crashed"].sum()) if ("next", "crashed") in batch.keys(True) else None,
        "final_checkpoint": int(batch["next", "checkpoint"][..., -1, :].sum())
        if ("next", "checkpoint") in batch.keys(True) else None,
    }


def _mean(values: list[float]) -> float:
    return math.fsum(values) / len(values)


class _timer:
    def __init__(self, totals: dict, key: str):
        self.totals, self.key = totals, key

    def __enter__(self):
        self.start = time.perf_counter()

    def __exit__(self, *exc):
        self.totals[self.key] += time.perf_counter() - self.start


def _progress_bar(cfg: RunConfig, initial: int = 0):
    from tqdm import tqdm

    return tqdm(total=cfg.episodes, initial=initial, disable=not cfg.progress, unit="ep", dynamic_ncols=True,
                desc=f"{cfg.algo.name}/{cfg.er.name}/seed{cfg.seed}")
