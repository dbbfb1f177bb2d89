"""Particle-world environments (MPE2 predator-prey, speaker-listener) and the referential game.

Each env is available two ways: as a PettingZoo ``ParallelEnv`` (``make_<env>``) for standalone use and the
PettingZoo test-suite, and behind the array-shaped ``BatchedEnv`` API (``make_<env>_batch``) for actors.
"""

from convoy.envs.particle.batch import ParallelEnvBatch
from convoy.envs.particle.predator_prey import (
    PredatorPreyConfig,
    PredatorPreyEnv,
    capture_rewards,
    evade_action,
    make_predator_prey,
    make_predator_prey_batch,
)
from convoy.envs.particle.referential import (
    ReferentialBatch,
    ReferentialConfig,
    ReferentialEnv,
    make_referential,
    make_referential_batch,
)
from convoy.envs.particle.speaker_listener import (
    SpeakerListenerConfig,
    SpeakerListenerEnv,
    make_speaker_listener,
    make_speaker_listener_batch,
)

__all__ = [
    "ParallelEnvBatch",
    "PredatorPreyConfig",
    "PredatorPreyEnv",
    "ReferentialBatch",
    "ReferentialConfig",
    "ReferentialEnv",
    "SpeakerListenerConfig",
    "SpeakerListenerEnv",
    "capture_rewards",
    "evade_action",
    "make_predator_prey",
    "make_predator_prey_batch",
    "make_referential",
    "make_referential_batch",
    "make_speaker_listener",
    "make_speaker_listener_batch",
]
