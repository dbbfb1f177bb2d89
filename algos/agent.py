"""Build the learning agent a job asks for: an algorithm, or hierarchical DQN wrapped around one, its replay
allocated for the job's steps (not all of ``replay_capacity``)."""

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
    agent: Agent
    if job.hierarchical:
        from convoy.algos.hierarchy import HierarchicalAgent

        agent = HierarchicalAgent(job, spec, device=dev)
        if run_configs is not None:
            agent.set_run_configs(list(run_configs))
    else:
        agent = make_algorithm(job.algo, spec, job.algo_config(), dev, job.seeds or job.seed, run_configs)
    agent.reserve_replay(max_env_steps(job, agent.chunk_len))
    return agent


def max_env_steps(job: JobConfig, chunk_len: int) -> int:
    """The most env steps one run of ``job`` observes (summed over its envs, as ``job.steps`` counts them): its
    budget and less than one more chunk, as the run ends at the first chunk at or past it — a chunk being
    ``num_envs`` envs × the actors' chunk length (in one process, ``chunk_len`` steps: never more). A resumed run
    is built for its new budget, so this holds for it too."""
    return job.steps + job.num_envs * job.runtime.chunk_len(chunk_len)
