"""The training engine: run configuration, the population loop, checkpoints, run folders,
numerics and versions, and evaluation of trained policies (``train.py``, ``evaluate.py``)."""
