"""The racing task: one simulator (``RacingSim``) behind a Gymnasium and a TorchRL environment.

Importing this package registers ``racing/Racing-v0`` with Gymnasium: ``gym.make`` gives one car
(``RacingEnv``), ``gym.make_vec`` N cars in one batched simulator (``RacingVectorEnv``). The TorchRL
environment, ``RacingTorchEnv``, is imported on first use (it needs torch and torchrl).
"""

from gymnasium.envs.registration import register, registry

from racing.config import PAPER_TRACK_SEEDS, RacingConfig
from racing.gym_env import RacingEnv
from racing.sim import RacingSim
from racing.track import Track, layout_track, track_from_seed
from racing.vector_env import RacingVectorEnv

ENV_ID = "racing/Racing-v0"

if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="racing.gym_env:RacingEnv", vector_entry_point="racing.vector_env:RacingVectorEnv",
             max_episode_steps=None)

__all__ = ["ENV_ID", "PAPER_TRACK_SEEDS", "RacingConfig", "RacingEnv", "RacingSim", "RacingTorchEnv", "RacingVectorEnv",
           "Track", "layout_track", "track_from_seed"]


def __getattr__(name):
    if name == "RacingTorchEnv":
        from racing.torchrl_env import RacingTorchEnv

        return RacingTorchEnv
    raise AttributeError(f"module 'racing' has no attribute {name!r}")
