"""The reactive ceiling from above, by direct policy search (docs/beyond.md): evolution strategies over the
weights of a deterministic actor that sees only the observation (five rays and the speed), started from a
finished run's actor (a Gaussian actor's mean: its deterministic policy), on that run's track.

Each generation draws ``pairs`` Gaussian perturbations of the weights, scores the ``2 x pairs`` mirrored
candidates on the same ``episodes`` fresh start states (one batched ``racing.sim.RacingSim``, every candidate
on every start state at once: common random numbers), and moves the weights along the perturbations weighted
by their centred ranks (antithetic OpenAI-ES, Adam on the weights; Salimans et al., 2017). Every
``choose_every`` generations the current weights are scored on the choice set (start seeds ``CHOICE_SEED`` +
k); the best so far is kept, the start included. The chosen weights, and the start, are then scored by the
evaluation protocol (``engine.evaluation.evaluate``: the actor rebuilt as a run's, start seeds 0..k) and on
fresh start states (seeds ``SCORE_SEED`` + k): start states no step of the search or the choice saw.

    python -m pupil.search RUN [RUN ...] [--generations 300] [--pairs 32] [--sigma 0.02] [--lr 0.01]
                           [--episodes 8] [--processes 2] [--table search.csv] [--out FOLDER]

Per run (its track), one line per choice-set scoring, then a table: the start's and the chosen weights'
scores by the protocol and on fresh start states, as fractions of the oracle's score on the track
(``analysis/data/oracle*.csv``). ``--out`` keeps each track's chosen weights (``policy-<track>.pt``: the
start's actor's tensors and names, a Gaussian's mean moved to the found policy, its scale rows as they were),
which ``algo.td.start_from`` takes.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, field
from engine.budget import PROCESSES
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch

CHOICE_SEED = 10_000  # the choice set's start states: seeds CHOICE_SEED + k
SCORE_SEED = 20_000  # the fresh scoring episodes: seeds SCORE_SEED + k (the protocol's are 0..k)
SEARCH_SEEDS = (100_000, 2**31)
MAX_CARS = 100_000  # cars one generation drives at once (2 x pairs x episodes): of the order of 100 MB (simulator state and the actors' activations)  # each generation's start states are drawn from this range


@dataclass(frozen=True)
class SearchSettings:
    generations: int = 300
    pairs: int = 32  # mirrored perturbations per generation (2 x pairs candidates)
    sigma: float = 0.02  # the perturbations' standard deviation, in weight units
    lr: float = 0.01  # Adam's step on the weights
    episodes: int = 8  # start states per generation, shared by every candidate
    choose_every: int = 10  # generations between scorings on the choice set
    choice: int = 20  # episodes of the choice set
    protocol: int = 10  # episodes of the evaluation protocol (start seeds 0..protocol-1)
    score: int = 50  # fresh scoring episodes (start seeds SCORE_SEED + k)
    seed: int = 0  # the search's own draws (perturbations, start states), with the track's seed

    def __post_init__(self) -> None:
        for name in ("generations", "pairs", "episodes", "choose_every", "choice", "protocol", "score"):
            if not 1 <= getattr(self, name) <= 1_000_000:
                raise ValueError(f"{name} must be in [1, 1,000,000], got {getattr(self, name)}")
        if 2 * self.pairs * self.episodes > MAX_CARS:  # one batched simulator drives every candidate at once
            raise ValueError(f"2 x pairs x episodes is {2 * self.pairs * self.episodes:,} cars at once, above "
                             f"{MAX_CARS:,}; give fewer pairs or episodes")
        for name in ("sigma", "lr"):
            if not 0 < getattr(self, name) < 10:
                raise ValueError(f"{name} must be in (0, 10), got {getattr(self, name)}")


@dataclass
class SearchResult:
    track: int
    start: dict  # {"protocol": score, "fresh": score} of the start's deterministic policy
    found: dict  # the same of the chosen weights
    chosen_generation: int  # 0: the start itself was never beaten on the choice set
    choice: list = field(default_factory=list)  # (generation, choice-set score) of every scoring
    weights: dict = field(default_factory=dict)  # the chosen actor in the start's layout (a Gaussian's scale rows kept)
    seconds: float = 0.0


class Actor:
    """A one-hidden-layer tanh actor as flat weights ``[C, P]`` for C candidates: observation -> tanh actions."""

    def __init__(self, state: dict[str, torch.Tensor]):
        import torch

        names = sorted(k for k in state if k.endswith(".weight"))
        if len(names) != 2:
            raise ValueError(f"the search takes an actor of one hidden layer; this one has {len(names)} layers")
        self.names = [n for layer in names for n in (layer, layer.removesuffix("weight") + "bias")]
        self.shapes = [tuple(state[n].shape) for n in self.names]
        self.sizes = [math.prod(s) for s in self.shapes]
        self.theta = torch.cat([state[n].double().reshape(-1) for n in self.names])

    def unflatten(self, flat: torch.Tensor) -> list[torch.Tensor]:
        parts = flat.split(self.sizes, dim=-1)
        return [p.reshape(flat.shape[0], *s) for p, s in zip(parts, self.shapes)]

    def state(self, flat: torch.Tensor) -> dict[str, torch.Tensor]:
        return {n: p[0].float().clone() for n, p in zip(self.names, self.unflatten(flat.reshape(1, -1)))}

    def act(self, flat: torch.Tensor, observation: torch.Tensor) -> torch.Tensor:
        """``[C, K, obs] -> [C, K, 2]`` actions of the C candidates."""
        import torch

        w0, b0, w1, b1 = self.unflatten(flat)
        hidden = torch.tanh(observation @ w0.transpose(1, 2) + b0[:, None])
        return torch.tanh(hidden @ w1.transpose(1, 2) + b1[:, None])


def in_layout(found: dict[str, torch.Tensor], start: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Deterministic weights ``found`` in the layout of the actor the search started from ``start``: a Gaussian's
    last layer keeps its scale rows (the search moved only the mean's), so its mean is the found policy."""
    import torch

    out = {}
    for name, value in start.items():
        mine = found[name]
        out[name] = torch.cat([mine, value[mine.shape[0]:]]) if value.shape[0] > mine.shape[0] else mine.clone()
    return out


def deterministic_state(state: dict[str, torch.Tensor], gaussian: bool) -> dict[str, torch.Tensor]:
    """A saved actor's weights as a deterministic actor's: a Gaussian's last layer keeps its mean's rows."""
    if not gaussian:
        return dict(state)
    from learners.td.learner import gaussian_mean

    last = max(k for k in state if k.endswith(".weight"))
    return gaussian_mean(state, last, state[last].shape[0] // 2)


def returns(actor: Actor, flat: torch.Tensor, track: int, seeds: list[int], config) -> np.ndarray:
    """Total rewards ``[C, K]`` of C candidates, each from the start states of ``seeds`` (K), on ``track``:
    one batched simulator; an episode ends at the time limit or when its car finishes (as the env's)."""
    import torch

    from racing.sim import RacingSim

    c, k = flat.shape[0], len(seeds)
    sim = RacingSim(c * k, track, config)
    sim.seed([s for _ in range(c) for s in seeds])
    sim.reset()
    total, alive = np.zeros(c * k), np.ones(c * k, dtype=bool)
    while alive.any():
        observation = torch.as_tensor(sim.observe().astype(np.float32)).double().reshape(c, k, -1)  # as the env's
        action = actor.act(flat, observation).reshape(c * k, 2).numpy()
        reward, terminated, truncated, _ = sim.step(action[:, 0].copy(), action[:, 1].copy())
        total += np.where(alive, reward, 0.0)
        alive &= ~(terminated | truncated)
    return total.reshape(c, k)


def centred_ranks(values: np.ndarray) -> np.ndarray:
    """Ranks scaled to [-0.5, 0.5] (ties broken by order)."""
    ranks = np.empty(len(values))
    ranks[np.argsort(values, kind="stable")] = np.arange(len(values))
    return ranks / max(1, len(values) - 1) - 0.5


def search(track: int, state: dict[str, torch.Tensor], gaussian: bool, settings: SearchSettings = SearchSettings(),
           network: dict | None = None, env_options: dict | None = None, progress=None) -> SearchResult:
    """The search on ``track`` from an actor's saved weights ``state`` (``gaussian``: a Gaussian actor's)."""
    import time

    import torch

    from engine.evaluation import evaluate, make_policy
    from racing.config import RacingConfig

    start_time = time.perf_counter()
    config = RacingConfig(**(env_options or {}))
    actor = Actor(deterministic_state(state, gaussian))
    theta = actor.theta.clone()
    rng = np.random.default_rng([settings.seed, track])
    noise = torch.Generator().manual_seed(int(rng.integers(2**62)))
    m, v = torch.zeros_like(theta), torch.zeros_like(theta)
    choice_seeds = [CHOICE_SEED + i for i in range(settings.choice)]

    def on_choice(flat: torch.Tensor) -> float:
        return float(returns(actor, flat.reshape(1, -1), track, choice_seeds, config).mean())

    best, best_score, chosen = theta.clone(), on_choice(theta), 0
    history = [(0, best_score)]
    for generation in range(1, settings.generations + 1):
        eps = torch.randn(settings.pairs, theta.numel(), generator=noise, dtype=torch.float64)
        candidates = torch.cat([theta + settings.sigma * eps, theta - settings.sigma * eps])
        seeds = rng.integers(*SEARCH_SEEDS, size=settings.episodes).tolist()
        fitness = returns(actor, candidates, track, seeds, config).mean(1)
        u = torch.as_tensor(centred_ranks(fitness))
        grad = (u[:settings.pairs] - u[settings.pairs:]) @ eps / (2 * settings.pairs * settings.sigma)
        m = 0.9 * m + 0.1 * grad
        v = 0.999 * v + 0.001 * grad.square()
        step = settings.lr * (m / (1 - 0.9**generation)) / ((v / (1 - 0.999**generation)).sqrt() + 1e-8)
        theta = theta + step  # ascent
        if generation % settings.choose_every == 0 or generation == settings.generations:
            score = on_choice(theta)
            history.append((generation, score))
            if score > best_score:
                best, best_score, chosen = theta.clone(), score, generation
            if progress is not None:
                progress(f"track {track}: generation {generation}, choice set {score:.2f} (best {best_score:.2f} "
                         f"at generation {chosen}), candidates {fitness.mean():.2f}")

    net = network or {"actor_hidden": [actor.shapes[0][0]], "activation": "tanh"}

    def scores(flat: torch.Tensor) -> dict:
        policy = make_policy("td3", net, config.obs_size, actor.state(flat))  # a deterministic actor, as a run's
        env = {"env": {"options": dict(env_options or {})}}
        fresh = [evaluate(policy, env, [track], 1, seed=SCORE_SEED + i)[track] for i in range(settings.score)]
        return {"protocol": evaluate(policy, env, [track], settings.protocol)[track],
                "fresh": math.fsum(fresh) / len(fresh), "fresh_episodes": fresh}

    return SearchResult(track, scores(actor.theta), scores(best), chosen, history, in_layout(actor.state(best), state),
                        round(time.perf_counter() - start_time, 1))


def _one(args: tuple) -> SearchResult:
    return _search_run(*args)


def _search_run(folder: Path, settings: SearchSettings) -> SearchResult:
    from engine.checkpoint import load_tensors
    from engine.limits import weights_limit
    from engine.evaluation import load_policy, own_track, saved_actor
    from learners.registry import spec

    _, recorded = load_policy(folder)  # a finished, intact run whose actor builds (every tool's check)
    if recorded["env"].get("track") != "fixed":
        raise ValueError(f"{folder}: the search drives one fixed track; this run trained on env.track="
                         f"{recorded['env'].get('track')}")
    if recorded["network"].get("activation") != "tanh":
        raise ValueError(f"{folder}: the search's actor computes tanh hidden units; this run's are "
                         f"{recorded['network'].get('activation')}")
    if recorded["env"].get("past_steps", 0) or recorded["algo"].get("td", {}).get("observation_norm"):
        raise ValueError(f"{folder}: the search takes an actor that reads the observation as it is (no past steps, "
                         "no observation normalisation)")
    state = saved_actor(load_tensors(folder / "actor.pt", "actor", limit=weights_limit(recorded["network"], "actor")))
    track = own_track(recorded)
    return search(track, state, spec(recorded["algo"]["loss"]).gaussian_actor, settings,
                  network=recorded["network"], env_options=recorded["env"].get("options") or {}, progress=_say)


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


COLUMNS = ("track", "oracle", "start_protocol", "found_protocol", "start_fresh", "found_fresh", "start_fraction",
           "found_fraction", "gain_fresh", "gain_low", "gain_high", "chosen_generation", "seconds")


def paired_interval(a: list[float], b: list[float]) -> tuple[float, float]:
    """A 95% normal interval of the mean of ``b - a`` over paired episodes."""
    d = np.asarray(b) - np.asarray(a)
    half = 1.96 * d.std(ddof=1) / math.sqrt(len(d)) if len(d) > 1 else float("nan")
    return float(d.mean() - half), float(d.mean() + half)


def rows_of(results: list[SearchResult], oracle: dict) -> list[dict]:
    rows = []
    for r in results:
        o = oracle.get(r.track)
        rows.append({"track": r.track, "oracle": o, "start_protocol": r.start["protocol"],
                     "found_protocol": r.found["protocol"], "start_fresh": r.start["fresh"],
                     "found_fresh": r.found["fresh"],
                     "start_fraction": r.start["fresh"] / o if o else None,
                     "found_fraction": r.found["fresh"] / o if o else None,
                     "gain_fresh": (r.found["fresh"] - r.start["fresh"]) / o if o else None,
                     **dict(zip(("gain_low", "gain_high"),
                                (v / o if o else None for v in paired_interval(r.start["fresh_episodes"],
                                                                               r.found["fresh_episodes"])))),
                     "chosen_generation": r.chosen_generation, "seconds": r.seconds})
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", type=Path, nargs="+", help="finished runs on fixed tracks: their actors start the search")
    defaults = SearchSettings()
    for name, kind in (("generations", int), ("pairs", int), ("sigma", float), ("lr", float), ("episodes", int),
                       ("choose_every", int), ("choice", int), ("protocol", int), ("score", int), ("seed", int)):
        parser.add_argument(f"--{name.replace('_', '-')}", type=kind, default=getattr(defaults, name),
                            help=f"default {getattr(defaults, name)}")
    parser.add_argument("--processes", type=PROCESSES, default=1, help="runs searched at once, one process each")
    parser.add_argument("--table", type=Path, default=None, help="also write the rows as CSV")
    parser.add_argument("--out", type=Path, default=None, help="a folder for each track's chosen weights")
    args = parser.parse_args(argv)
    from engine.tool_output import check_output_folder, check_outputs

    check_outputs(parser, reads=args.runs, table=args.table)
    if args.out is not None:
        check_output_folder(parser, "--out", args.out)
    try:
        settings = SearchSettings(**{k: getattr(args, k) for k in SearchSettings.__dataclass_fields__})
    except ValueError as err:
        parser.error(str(err))
    from engine import numerics
    from engine.outputs import RunFolderError, read_summary
    from engine.pool import run_jobs
    from engine.rundir import runs_numerics
    from engine.runset import read_runs

    try:
        runs = read_runs(args.runs, say="search").runs  # each run once (named twice, a link, a copy)
        numerics.apply(runs_numerics(runs))  # before torch loads: the runs' own numerics
    except (RunFolderError, numerics.NumericsError) as err:
        print(f"search: {err}", file=sys.stderr)
        return 2
    from analysis.report import read_oracles

    tracks = {}
    for run in runs:  # each track's result is one row and one policy-<track>.pt
        try:
            summary = read_summary(run) or {}
        except RunFolderError:
            continue  # the search's own reading says what is wrong with it
        if summary.get("seed") in tracks:
            print(f"search: {tracks[summary['seed']]} and {run} trained on track {summary['seed']}; search one run a "
                  "track (their results would share a row and policy file)", file=sys.stderr)
            return 2
        tracks[summary.get("seed")] = run
    try:
        results = run_jobs(_one, [(run, settings) for run in runs], args.processes, numerics.applied())
    except (RunFolderError, ValueError) as err:
        print(f"search: {err}", file=sys.stderr)
        return 2
    rows = rows_of(results, read_oracles())
    print("| " + " | ".join(COLUMNS) + " |")
    print("|" + "---|" * len(COLUMNS))
    for row in rows:
        print("| " + " | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in row.values()) + " |")
    if args.table is not None:
        from engine.outputs import write_table

        write_table(args.table, rows)
    if args.out is not None:
        from door import files
        from engine.checkpoint import save_tensors

        files.folder(args.out, create=True)
        for r in results:
            save_tensors(args.out / f"policy-{r.track}.pt", r.weights)
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("pupil.search", main))
