"""Networks taught by the oracle (``dagger``: the reactive ceiling; ``imitate.py``)."""
