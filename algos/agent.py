"""Build the learning agent a job asks for: an algorithm, or hierarchical DQN wrapped around one."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from convoy.algos.algorithm import Agent
from convoy.algos.registry import make_algorithm
from convoy.config import AlgoConfig, JobConfig
from convoy.envs.batched import EnvSpec


def make_agent(
    job: JobConfig,
    spec: EnvSpec,
    device: str | torch.device | None = None,
    run_configs: Sequence[AlgoConfig] | None = None,
) -> Agent:
    """The job's algorithm for ``spec`` (its env defaults resolved), hierarchical when ``job.hierarchical``; a
    population of ``len(job.seeds)`` runs when the job has seeds, ``run_configs`` its runs' own hyper-parameters."""
    dev = job.device if device is None else device
    if job.hierarchical:
        from convoy.algos.hierarchy import HierarchicalAgent

        agent = HierarchicalAgent(job, spec, device=dev)
        if run_configs is not None:
            agent.set_run_configs(list(run_configs))
        return agent
    return make_algorithm(job.algo, spec, job.algo_config(), dev, job.seeds or job.seed, run_configs)
