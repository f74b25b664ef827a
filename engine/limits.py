"""The RAM a run will need, checked before any work (torch-free).

Each configuration value that sets an allocation has a ceiling where it is declared (its field's
``learners.options.capped``, checked as the configuration is built; the simulator's own,
``racing.config.MAX_SEGMENTS``, ``MAX_STEPS`` and ``MAX_RAYS``, and a track file's,
``racing.track_file.MAX_ROWS``, where those values are read; conf/ names each). Values under their
ceilings can still add up to more than a machine has:

``check_ram``, before a run writes anything (train.py, and the sweeper for every job), sets the
RAM a run will need, estimated from its sizes (``estimate``: replay memory and its checkpoint copies,
an episode's collected steps, the tracks' ray tables, networks with their optimiser state, the update
steps' records, a minibatch's activations, and the process itself), each part from what a run was
measured to allocate per step and per member (``speed/memory_estimate.py`` prints the estimate beside
measured peaks over a grid of sizes: each within 1.5 times of its peak), against the RAM the machine
has available (``available_bytes``: the kernel's MemAvailable, or a cgroup's limit if lower). A run
that would not fit is refused with the estimate, part by part. The per-step parts are set near the
middle of what was measured (one configuration's peak varies between processes, by up to 1.65
times for Monte-Carlo populations); the estimate is not a promise that a run it allows fits beside
other work.
"""

from __future__ import annotations

import math

from learners.options import ConfigError

TRANSITION_BYTES = 32  # a stored transition besides its two observations (measured in all: 44 bytes for the paper's
#                       learners, 70 for SAC's with priorities, at 6 observations)
OBSERVATION_BYTES = 8  # per observation of a stored transition (float32, and the next state's)
TABLE_BYTES = 16  # a track's ray tables, per squared checkpoint, kept (racing.physics builds N x 2N tables;
#                  building one takes 9 times that at its peak: measured 3.6 GB at 5,000 checkpoints)
CHECKPOINT_COPIES = 2  # a checkpoint holds the whole replay storage (allocated at its full size), serialised and read
# A collected step of the whole population (one step of every car) is about a dozen small tensors, each a few
# hundred bytes of bookkeeping whatever its size, kept until the episode is stacked; TorchRL's collector adds a
# TensorDict per step around them. Measured (speed/memory_estimate.py: peak RSS of one-episode runs of 200 to
# 200,000 steps and 1 to 9 members):
COLLECTED_STEP_BYTES = {"direct": 5_400, "torchrl": 7_300}
# A Monte-Carlo population's step costs about as much again per member beyond the first (measured, not itemised:
# 6.9 KB per added member from 3 to 9 members; an off-policy population's steps do not grow so).
MONTE_CARLO_MEMBER_STEP_BYTES = 6_500
MEMBER_STEP_BYTES = 100  # per member and step besides: its rows of the stacked episode (and 16 bytes per observation)
UPDATE_STEP_BYTES = 600  # per member and gradient step of an off-policy episode: the step's diagnostics, kept until
#                         the episode's end (learners.base.MetricTotals), and what the allocator keeps around them
#                         (measured: nothing visible at 3 members, 17 KB per environment step at 9 members instead of 8)
PROCESS_BYTES = 370 * 2**20  # torch, the simulator, Hydra and Python themselves (a 200-step run peaks at 380-390 MB)
PARAMETER_COPIES = 5  # a parameter, its gradient, Adam's two moments, and a target network's copy
ACTIVATION_COPIES = 8  # per unit of a layer and row of a minibatch: forward values, gradients, temporaries


def _mlp_parameters(sizes: list[int]) -> int:
    return sum((a + 1) * b for a, b in zip(sizes, sizes[1:]))


def estimate(cfg) -> dict[str, int]:
    """Bytes a run of ``cfg`` (a ``RunConfig``) will hold at its peak, by part (a low estimate)."""
    from racing.config import RacingConfig

    options = RacingConfig(**cfg.env.options)
    members, steps, obs = len(cfg.members), options.max_steps, cfg.env.observation_size  # env.past_steps's width
    checkpoints = options.num_segments
    if cfg.env.track_file is not None:  # the file decides (validated already: it reads)
        from racing.track_file import read_rows

        checkpoints = len(read_rows(cfg.env.track_file)[0])
    algo, net = cfg.algo, cfg.network
    critics, outputs, reads_action = algo.learner.critic(algo)  # its critic networks' number and shape
    critic_inputs = obs + 2 * reads_action
    critic_layers = list(net.critic_hidden)
    if algo.td is not None and algo.td.critic_blocks:
        width = algo.td.critic_width or net.critic_hidden[0]
        critic_layers = [width] * (1 + 2 * algo.td.critic_blocks)
    actor = _mlp_parameters([obs, *net.actor_hidden, 4])
    critic = _mlp_parameters([critic_inputs, *critic_layers, outputs])
    parameters, widest, layers = actor + critics * critic, max((*net.actor_hidden, *critic_layers)), max(
        len(net.actor_hidden), len(critic_layers))
    if algo.learner.networks is not None:  # networks its own options shape (SimbaV2's, the planner's)
        parameters, widest, layers = algo.learner.networks(algo, obs, 2)
    stored = cfg.er.buffer_size if cfg.er.train_on_memory else 0  # allocated whole, saved whole by checkpoints
    transition = TRANSITION_BYTES + OBSERVATION_BYTES * obs
    minibatch = max(1, round(algo.minibatch_size * cfg.er.minibatch_fraction))
    rows = algo.learner.rows(algo, minibatch)  # SPG scores sampled actions; Trust-PCL's minibatch counts sub-episodes
    return {
        "replay memory": members * stored * transition,
        "checkpoints": members * stored * transition * CHECKPOINT_COPIES if cfg.checkpoint_every else 0,
        "episodes": steps * (COLLECTED_STEP_BYTES[cfg.env.collector]
                             + (0 if algo.td is not None else (members - 1) * MONTE_CARLO_MEMBER_STEP_BYTES)
                             + members * (MEMBER_STEP_BYTES + 16 * obs)),
        "track tables": (members + 8) * TABLE_BYTES * checkpoints**2,
        "networks": members * parameters * 4 * PARAMETER_COPIES,
        "acting": members * algo.learner.acting(algo, steps) * 4,
        "update records": round(members * steps * algo.td.updates_per_step * UPDATE_STEP_BYTES) if algo.td else 0,
        "activations": members * rows * widest * layers * (critics if algo.td is not None else 1) * 4
        * ACTIVATION_COPIES,
        "process": PROCESS_BYTES,
    }


def available_bytes() -> int | None:
    """Memory this process may still take: MemAvailable (``/proc/meminfo``), or the cgroup's limit
    less its usage if that is lower; None where neither can be read (not Linux)."""
    from door import files

    def system(path: str) -> str:
        return files.read_text(path, 1 << 16, "system file", follow=True)

    found = []
    try:
        for line in system("/proc/meminfo").splitlines():
            if line.startswith("MemAvailable:"):
                found.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    try:
        limit = system("/sys/fs/cgroup/memory.max").strip()
        if limit != "max":
            used = int(system("/sys/fs/cgroup/memory.current"))
            found.append(int(limit) - used)
    except (OSError, ValueError):
        pass
    return min(found) if found else None


def _gb(size: float) -> str:
    return f"{size / 2**30:.1f} GB" if size >= 2**30 else f"{math.ceil(size / 2**20)} MB"


def check_ram(cfg, available: int | None = None) -> None:
    """``ConfigError`` with the estimate if a run of ``cfg`` would not fit in ``available`` bytes
    (default: ``available_bytes()``; no check where that is unknown)."""
    available = available_bytes() if available is None else available
    if available is None:
        return
    parts = estimate(cfg)
    total = sum(parts.values())
    if total > available:
        detail = ", ".join(f"{name} {_gb(size)}" for name, size in parts.items() if size >= 2**20)
        raise ConfigError(f"this run needs about {_gb(total)} of RAM ({detail}) and the machine has "
                          f"{_gb(max(available, 0))} available; make it smaller (er.buffer_size, seeds, "
                          "env.options.max_steps, network sizes) or split it (processes, or several commands)")


# A weights file's size, bounded by what its shapes may need before it is read (``weights_limit``): a file of
# tensors is refused unread past it (a valid 4.8 GB tensors file given to algo.td.start_from was read whole,
# 13.7 GB resident, before its shapes were checked). Generous by design: any learner's networks of those
# hidden layers fit (an input of up to INPUT_BOUND values, up to OUTPUT_BOUND outputs, blocks up to WIDENING
# times wider inside, float64, CRITIC_COPIES Q-networks), and a file that big is still checked shape by shape.
INPUT_BOUND = 1024
OUTPUT_BOUND = 64
WIDENING = 8
CRITIC_COPIES = 16
FILE_SLACK = 1 << 20  # bytes: torch's zip headers, names and pickle


def weights_limit(network, what: str) -> int:
    """The most bytes an ``"actor"`` or ``"critic"`` weights file of networks with ``network``'s hidden layers
    (a run's recorded ``settings.network``, or its config) may hold; past it, the file is refused unread."""
    get = network.get if isinstance(network, dict) else lambda key, default=None: getattr(network, key, default)
    hidden = [int(width) for width in (get(f"{what}_hidden") or ()) if isinstance(width, int) and width > 0]
    widths = [INPUT_BOUND, *hidden, OUTPUT_BOUND]
    parameters = sum((a + 1) * b for a, b in zip(widths, widths[1:]))
    return 8 * WIDENING * parameters * (CRITIC_COPIES if what == "critic" else 1) + FILE_SLACK
