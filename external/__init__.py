"""Reference learners from other libraries, run as this project's run folders (``sb3``:
Stable-Baselines3's SAC and PPO with their defaults; ``baseline.py``)."""
