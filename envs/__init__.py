"""Convoy's environments: the treadmill highway and the particle envs, behind one batched interface.

Importing this package registers ``convoy/Treadmill-v0`` with Gymnasium. It imports only Convoy's
shared helpers (``convoy.validation``, ``convoy.stats``), so every other package can depend on it.
"""

import gymnasium

from convoy.envs.batched import BatchedEnv, EnvSpec, StepResult
from convoy.envs.channel import ChannelConfig, MessageChannel
from convoy.envs.registry import ENVS, make_batched, make_parallel

TREADMILL_GYM_ID = "convoy/Treadmill-v0"

if TREADMILL_GYM_ID not in gymnasium.registry:
    gymnasium.register(
        id=TREADMILL_GYM_ID,
        entry_point="convoy.envs.treadmill.gym_env:TreadmillGymEnv",
        max_episode_steps=None,  # the env truncates itself at its own max_steps
    )

__all__ = [
    "ENVS",
    "TREADMILL_GYM_ID",
    "BatchedEnv",
    "ChannelConfig",
    "EnvSpec",
    "MessageChannel",
    "StepResult",
    "make_batched",
    "make_parallel",
]
