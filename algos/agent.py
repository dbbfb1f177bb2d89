"""Build the learning agent a job asks for: an algorithm, or hierarchical DQN wrapped around one."""

from __future__ import annotations

import torch

from convoy.algos.algorithm import Agent
from convoy.algos.registry import make_algorithm
from convoy.config import JobConfig
from convoy.envs.batched import EnvSpec


def make_agent(job: JobConfig, spec: EnvSpec, device: str | torch.device | None = None) -> Agent:
    """The job's algorithm for ``spec`` (its env defaults resolved), hierarchical when ``job.hierarchical``; a
    population of ``len(job.seeds)`` runs when the job has seeds."""
    dev = job.device if device is None else device
    if job.hierarchical:
        from convoy.algos.hierarchy import HierarchicalAgent

        return HierarchicalAgent(job, spec, device=dev)
    return make_algorithm(job.algo, spec, job.algo_config(), device=dev, seed=job.seeds or job.seed)
