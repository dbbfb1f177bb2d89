"""The treadmill highway of the paper (section 5.1): one batched engine and thin front ends."""

from convoy.envs.treadmill.config import N_ACTIONS, TreadmillConfig
from convoy.envs.treadmill.engine import TreadmillEngine, distance
from convoy.envs.treadmill.gym_env import TreadmillGymEnv
from convoy.envs.treadmill.pettingzoo_env import TreadmillParallelEnv
from convoy.envs.treadmill.references import REFERENCES, reference_policy
from convoy.envs.treadmill.render import render_frame, write_gif
from convoy.envs.treadmill.scripted import full_information_actions, scripted_actions

__all__ = [
    "N_ACTIONS",
    "REFERENCES",
    "TreadmillConfig",
    "TreadmillEngine",
    "TreadmillGymEnv",
    "TreadmillParallelEnv",
    "distance",
    "full_information_actions",
    "reference_policy",
    "render_frame",
    "scripted_actions",
    "write_gif",
]
