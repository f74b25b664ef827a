"""Loss modules of the paper's algorithms, as TorchRL ``LossModule``s.

Each exposes ``critic_loss(td)`` and ``actor_loss(td)`` (the two phases are optimised
separately), ``forward(td)`` with both, and three phase hooks the training loop calls:
``before_critic_phase(data)``, ``before_actor_phase(data)`` and ``after_actor_phase()``.
The arithmetic lives in ``losses.functional``.
"""

from losses.ppo import LogClipPPOLoss
from losses.spg import SPGLoss

__all__ = ["LogClipPPOLoss", "SPGLoss"]
