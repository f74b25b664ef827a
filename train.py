"""Train one cell of the paper's table: ``python train.py algo=spg_p er=hybrid seed=3``, or one
run per seed in one process: ``python train.py algo=spg_p er=hybrid 'seeds=[3,4,5]'``.

A run writes into its folder (``outputs/runs/<algo>/<er>/seed<seed>`` by default, or the
sweep's subfolder with ``-m``): ``metrics.csv``, ``summary.json``, ``actor.pt``, ``critic.pt``,
TorchRL logs and the resolved configuration in ``.hydra/`` (written once the run is sure to
start: a refused command leaves the folder as it was). With ``seeds``, each member writes that
into ``outputs/runs/<algo>/<er>/seed<seed>/``. See ``conf/config.yaml`` for every option and
``engine/rundir.py`` for the rules of a run folder (finished, resumable, damaged; its lock).

Exit status: 0 when every run finished (its last line says where and how well), 2 when the
command was refused (one line saying why; nothing was written), 1 for a full disk, 130 or 143
when stopped by SIGINT or SIGTERM (one line: where it was saved; the same command resumes).
"""

from __future__ import annotations

import os

from engine import command  # light (the standard library): the signal handlers before the slow imports

if __name__ == "__main__":
    command.stop_early_on_signals()  # one line, not a traceback, while torch and Hydra load

import hydra  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from engine.config import register_resolvers  # noqa: E402

os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")  # torchrl's INFO lines (set before it loads)
register_resolvers()  # the run folder's name (conf/config.yaml) uses one


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float | list | None:
    # 1. The configuration, typed and checked (engine/config.py): a bad value ends here in one line,
    #    before anything is written and before torch loads (the numerics mode is set first).
    settings, run_cfg = command.validated(cfg)
    from engine.runner import train_population  # after validation: torch loads slowly

    # 2. Train: every member of the population (a solo run is one of one) in its run folder. The env,
    #    the TorchRL Collector, the replay memory, the learner's loss modules and optimisers and the
    #    episode loop are engine/runner.py's; the session ends a refused, stopped or failed run in one line.
    with command.session(cfg, settings) as run:
        summaries = train_population(run_cfg, run.out_dir, settings, skipped=run.skipped, on_start=run.started,
                                     stop_file=run.stop_file, root=run.root)

    # 3. Report: one line per run (and per member already finished, skipped).
    run.report(run_cfg, summaries)
    finals = [s["final_mean"] for s in summaries]
    return finals[0] if run_cfg.seeds is None else finals


if __name__ == "__main__":
    command.run(main)
