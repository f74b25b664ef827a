"""Train one cell of the paper's table: ``python train.py algo=spg_p er=hybrid seed=3``.

Writes into the run's folder (``outputs/runs/<algo>/<er>/seed<seed>`` by default, or the
sweep's subfolder with ``-m``): ``metrics.csv``, ``summary.json``, ``actor.pt``, ``critic.pt``,
TorchRL logs and Hydra's ``.hydra/``. See ``conf/config.yaml`` for every option.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from experiment.config import ConfigError, RunConfig

os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")  # torchrl's INFO lines (set before it loads)


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    settings = OmegaConf.to_container(cfg, resolve=True)
    try:
        run_cfg = RunConfig.from_mapping(settings)
    except ConfigError as err:
        print(f"Invalid configuration: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    from experiment.checkpoint import CHECKPOINT_FILE, CheckpointError
    from experiment.runner import finished_run, train  # after validation: torch loads slowly
    from experiment.version import describe

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        done = finished_run(out_dir, settings, overwrite=run_cfg.overwrite)
        if done is not None:
            print(f"{out_dir}: already {done['status']} (final_mean {done['final_mean']}, "
                  f"{describe(done.get('code'))}); skipped", file=sys.stderr)
            return done["final_mean"]
        if run_cfg.overwrite:
            (out_dir / CHECKPOINT_FILE).unlink(missing_ok=True)
        return train(run_cfg, out_dir, settings)["final_mean"]
    except (ConfigError, CheckpointError) as err:
        print(f"Refusing to run: {err}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
