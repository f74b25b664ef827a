"""Train one cell of the paper's table: ``python train.py algo=spg_p er=hybrid seed=3``.

Writes into the run's folder (``outputs/runs/<algo>/<er>/seed<seed>`` by default, or the
sweep's subfolder with ``-m``): ``metrics.csv``, ``summary.json``, ``actor.pt``, ``critic.pt``,
TorchRL logs and Hydra's ``.hydra/``. See ``conf/config.yaml`` for every option.
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from experiment.config import ConfigError, RunConfig


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    try:
        run_cfg = RunConfig.from_mapping(OmegaConf.to_container(cfg, resolve=True))
    except ConfigError as err:
        print(f"Invalid configuration: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    from experiment.runner import finished_run, train  # after validation: torch loads slowly

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    settings = OmegaConf.to_container(cfg, resolve=True)
    try:
        done = finished_run(out_dir, settings, overwrite=run_cfg.overwrite)
    except ConfigError as err:
        print(f"Refusing to run: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    if done is not None:
        print(f"{out_dir}: already {done['status']} (final_mean {done['final_mean']}); skipped", file=sys.stderr)
        return done["final_mean"]
    summary = train(run_cfg, out_dir, settings)
    return summary["final_mean"]


if __name__ == "__main__":
    main()
