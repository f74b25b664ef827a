"""The project's Hydra launcher plugin (Hydra loads launchers only from ``hydra_plugins``):
``hydra/launcher=slurm`` (``conf/hydra/launcher/slurm.yaml``) uses ``slurm.SlurmLauncher``."""
