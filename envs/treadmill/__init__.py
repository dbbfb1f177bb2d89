"""The treadmill highway of the paper (section 5.1): one batched engine and thin front ends."""

from envs.treadmill.config import N_ACTIONS, TreadmillConfig
from envs.treadmill.engine import TreadmillEngine, distance
from envs.treadmill.gym_env import TreadmillGymEnv
from envs.treadmill.pettingzoo_env import TreadmillParallelEnv
from envs.treadmill.references import REFERENCES, reference_policy
from envs.treadmill.render import render_frame, write_gif
from envs.treadmill.scripted import full_information_actions, scripted_actions

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
