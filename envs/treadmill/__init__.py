"""The treadmill highway of the paper (section 5.1): one batched engine and thin front ends."""

from envs.treadmill.config import N_ACTIONS, TreadmillConfig
from envs.treadmill.engine import TreadmillEngine, torus_delta, torus_distance
from envs.treadmill.gym_env import TreadmillGymEnv
from envs.treadmill.pettingzoo_env import TreadmillParallelEnv
from envs.treadmill.render import render_frame, write_gif
from envs.treadmill.scripted import scripted_actions

__all__ = [
    "N_ACTIONS",
    "TreadmillConfig",
    "TreadmillEngine",
    "TreadmillGymEnv",
    "TreadmillParallelEnv",
    "render_frame",
    "scripted_actions",
    "torus_delta",
    "torus_distance",
    "write_gif",
]
