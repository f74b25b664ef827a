"""Train one cell of the paper's table: ``python train.py algo=spg_p er=hybrid seed=3``, or one
run per seed in one process: ``python train.py algo=spg_p er=hybrid 'seeds=[3,4,5]'``.

A run writes into its folder (``outputs/runs/<algo>/<er>/seed<seed>`` by default, or the
sweep's subfolder with ``-m``): ``metrics.csv``, ``summary.json``, ``actor.pt``, ``critic.pt``,
TorchRL logs and Hydra's ``.hydra/``. With ``seeds``, each member writes that into
``outputs/runs/<algo>/<er>/seed<seed>/``. See ``conf/config.yaml`` for every option.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from engine import numerics
from engine.config import ConfigError, RunConfig, register_resolvers

os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")  # torchrl's INFO lines (set before it loads)
register_resolvers()  # the run folder's name (conf/config.yaml) uses one


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float | list | None:
    settings = OmegaConf.to_container(cfg, resolve=True)
    try:
        run_cfg = RunConfig.from_mapping(settings)
    except ConfigError as err:
        print(f"Invalid configuration: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    try:
        numerics.apply(run_cfg.numerics)  # before torch loads: it reads the kernel settings then
    except numerics.NumericsError as err:
        print(f"Refusing to run: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    from engine.checkpoint import CheckpointError, in_folder
    from engine.runner import train_population  # after validation: torch loads slowly
    from engine.version import describe

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        if run_cfg.overwrite:
            for path in in_folder(out_dir):
                path.unlink()
        skipped: list[tuple[Path, dict]] = []
        summaries = train_population(run_cfg, out_dir, settings, skipped=skipped)
    except (ConfigError, CheckpointError, numerics.NumericsError) as err:
        print(f"Refusing to run: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    for folder, summary in skipped:
        print(f"{folder}: already {summary['status']} (final_mean {summary['final_mean']}, "
              f"{describe(summary.get('code'))}); skipped", file=sys.stderr)
    finals = [s["final_mean"] for s in summaries]
    return finals[0] if run_cfg.seeds is None else finals

if __name__ == "__main__":
    main()
