"""The data path: collecting episodes, Monte-Carlo returns and experience replay."""

from collectors.episodes import BACKENDS, ActingPolicy, DirectCollector, make_collector
from collectors.replay import ReplayMemory, ReplaySchedule, sample_minibatch, sample_sub_episodes
from collectors.returns import RETURN_KEY, STEPS_KEY, add_monte_carlo_returns, episode_transitions, n_step_transitions

__all__ = ["BACKENDS", "ActingPolicy", "DirectCollector", "RETURN_KEY", "ReplayMemory", "ReplaySchedule", "STEPS_KEY",
           "add_monte_carlo_returns", "episode_transitions", "make_collector", "n_step_transitions",
           "sample_minibatch", "sample_sub_episodes"]
