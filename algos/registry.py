"""Algorithm names → classes (``convoy.config.ALGORITHMS``), imported on first use: one module per algorithm."""

from __future__ import annotations

import importlib
from collections.abc import Sequence

import torch

from convoy.algos.algorithm import NetworkAgent
from convoy.config import ALGORITHMS, AlgoConfig, algo_name
from convoy.envs.batched import EnvSpec


def algorithm_class(name: str) -> type[NetworkAgent]:
    module, _, attr = ALGORITHMS[algo_name(name)].impl.partition(":")
    return getattr(importlib.import_module(module), attr)


def make_algorithm(
    name: str,
    spec: EnvSpec,
    cfg: AlgoConfig,
    device: str | torch.device = "auto",
    seed: int | Sequence[int] = 0,
    run_configs: Sequence[AlgoConfig] | None = None,
) -> NetworkAgent:
    """Build algorithm ``name`` for env ``spec`` with a resolved config (see ``convoy.config.resolve_algo``); a
    sequence of seeds makes a population, ``run_configs`` (one per seed) its runs' own hyper-parameters."""
    agent = algorithm_class(name)(spec, cfg, device=device, seed=seed)
    if run_configs is not None:
        agent.set_run_configs(run_configs)
    return agent
